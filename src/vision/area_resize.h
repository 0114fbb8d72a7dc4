// OpenCV's cv::resize(..., INTER_AREA) on interleaved uint8 images, bit for bit (checked against
// opencv-python-headless 4.13). GR00T N1.7's albumentations image path resizes every camera frame this way.
//
// Written here rather than linked: Tether does not depend on OpenCV, and one resize mode does not justify the
// dependency (its size, its build options, and its CPU dispatch that changes rounding between builds).
#pragma once

#include <cstdint>

#include "vision/image.h"

namespace tether::vision {

// `src` is in_h x in_w x channels (1..4), `dst` out_h x out_w x channels. Same as
// cv2.resize(src, (out_w, out_h), interpolation=cv2.INTER_AREA):
//   - both axes shrinking (or one unchanged) by whole factors: box average (2x2 rounds (sum + 2) >> 2, other
//     factors round sum * float(1/area) half to even);
//   - both axes shrinking (or one unchanged), otherwise: exact pixel-area weights in float32;
//   - any axis enlarging: OpenCV's bilinear stand-in for area, with its own coefficients and 11-bit fixed point.
// Throws invalid_argument on empty sizes, a null pointer or an unsupported channel count.
void resize_area(const uint8_t* src, int in_h, int in_w, int channels, int out_h, int out_w, uint8_t* dst);

// The same on an RGB image.
Image resize_area(const Image& img, int out_h, int out_w);

}  // namespace tether::vision
