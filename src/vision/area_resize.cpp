// OpenCV INTER_AREA for uint8, restated from the rules in OpenCV 4.13's imgproc/src/resize.cpp (cv::hal::resize and
// the area helpers it calls). Which rule runs is decided exactly as OpenCV decides it:
//
//   inv_x = double(out_w) / in_w, scale_x = 1 / inv_x (the same for y), k_x = round(scale_x);
//   scale_x >= 1 and scale_y >= 1:
//     both within DBL_EPSILON of the integers k_x, k_y  -> box average over k_y x k_x blocks
//     otherwise                                         -> fractional pixel-area weights
//   otherwise (some axis enlarges)                      -> bilinear stand-in, on both axes
//
// The rounding of each rule is OpenCV's, including the parts that differ between them: the 2x2 box rounds
// (sum + 2) >> 2 while other boxes round float(sum) * (1.f / area) half to even; the area weights are float32
// with separate multiply and add (OpenCV's baseline build has no FMA); the bilinear stand-in uses 11-bit weights
// and OpenCV's vertical shortcut ((w * (v >> 4)) >> 16, then (+2) >> 2). OpenCV's SIMD and scalar code paths
// compute the same values, so the result does not depend on how many pixels its vector loops cover.
#include "vision/area_resize.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include "core/error.h"

namespace tether::vision {

namespace {

// OpenCV's cvRound: to nearest, ties to even (what the SSE conversions do in the default rounding mode).
inline int round_even(double v) { return int(std::nearbyint(v)); }
inline int round_even(float v) { return int(std::nearbyintf(v)); }

// cvFloor on double and float.
inline int floor_int(double v) { return int(std::floor(v)); }
inline int floor_int(float v) { return int(std::floor(v)); }

// saturate_cast<uchar>(float) and saturate_cast<short>(float).
inline uint8_t saturate_u8(float v) { return uint8_t(std::clamp(round_even(v), 0, 255)); }
inline int16_t saturate_s16(float v) { return int16_t(std::clamp(round_even(v), -32768, 32767)); }

// ---------------------------------------------------------------- whole-factor box average

void box_average(const uint8_t* src, int in_w, int cn, int out_h, int out_w, int kx, int ky, uint8_t* dst) {
  const int64_t src_row = int64_t(in_w) * cn;
  const int64_t dst_row = int64_t(out_w) * cn;
  if (kx == 2 && ky == 2 && cn != 2) {
    // OpenCV's dedicated 2x2 routine (1, 3 and 4 channels) rounds half up in integers.
    for (int dy = 0; dy < out_h; ++dy) {
      const uint8_t* s0 = src + int64_t(2 * dy) * src_row;
      const uint8_t* s1 = s0 + src_row;
      uint8_t* d = dst + dy * dst_row;
      for (int dx = 0; dx < out_w; ++dx) {
        for (int c = 0; c < cn; ++c) {
          const int64_t i = int64_t(2 * dx) * cn + c;
          d[dx * cn + c] = uint8_t((s0[i] + s0[i + cn] + s1[i] + s1[i + cn] + 2) >> 2);
        }
      }
    }
    return;
  }
  const float inv_area = 1.f / float(kx * ky);
  for (int dy = 0; dy < out_h; ++dy) {
    uint8_t* d = dst + dy * dst_row;
    for (int dx = 0; dx < out_w; ++dx) {
      for (int c = 0; c < cn; ++c) {
        int sum = 0;
        for (int y = 0; y < ky; ++y) {
          const uint8_t* s = src + int64_t(dy * ky + y) * src_row + int64_t(dx * kx) * cn + c;
          for (int x = 0; x < kx; ++x) sum += s[x * cn];
        }
        d[dx * cn + c] = saturate_u8(float(sum) * inv_area);
      }
    }
  }
}

// ---------------------------------------------------------------- fractional area weights

struct AreaTap {
  int dst, src;  // pixel indices along one axis
  float weight;
};

// Each output cell [d * scale, (d + 1) * scale) takes the source pixels it overlaps, weighted by the overlap over
// the cell width (cut short at the image edge); partial overlaps under 1e-3 of a pixel are dropped.
std::vector<AreaTap> area_taps(int in, int out, double scale) {
  std::vector<AreaTap> taps;
  taps.reserve(size_t(in) * 2);
  for (int d = 0; d < out; ++d) {
    const double f1 = d * scale;
    const double f2 = f1 + scale;
    const double cell = std::min(scale, in - f1);
    int s1 = int(std::ceil(f1));
    int s2 = floor_int(f2);
    s2 = std::min(s2, in - 1);
    s1 = std::min(s1, s2);
    if (s1 - f1 > 1e-3) taps.push_back({d, s1 - 1, float((s1 - f1) / cell)});
    for (int s = s1; s < s2; ++s) taps.push_back({d, s, float(1.0 / cell)});
    if (f2 - s2 > 1e-3) taps.push_back({d, s2, float(std::min(std::min(f2 - s2, 1.), cell) / cell)});
  }
  return taps;
}

void area_weights(const uint8_t* src, int in_h, int in_w, int cn, int out_h, int out_w, double scale_x,
                  double scale_y, uint8_t* dst) {
  const std::vector<AreaTap> xt = area_taps(in_w, out_w, scale_x);
  const std::vector<AreaTap> yt = area_taps(in_h, out_h, scale_y);
  const int64_t src_row = int64_t(in_w) * cn;
  const size_t width = size_t(out_w) * cn;
  std::vector<float> buf(width), sum(width);
  size_t j = 0;
  for (int dy = 0; dy < out_h; ++dy) {
    bool first = true;
    for (; j < yt.size() && yt[j].dst == dy; ++j) {
      // One source row resampled horizontally...
      const uint8_t* row = src + int64_t(yt[j].src) * src_row;
      std::fill(buf.begin(), buf.end(), 0.0f);
      for (const AreaTap& t : xt) {
        for (int c = 0; c < cn; ++c) {
          float& b = buf[size_t(t.dst) * cn + c];
          b = b + float(row[int64_t(t.src) * cn + c]) * t.weight;
        }
      }
      // ...then added into the output row with its vertical weight.
      const float beta = yt[j].weight;
      if (first) {
        for (size_t i = 0; i < width; ++i) sum[i] = beta * buf[i];
      } else {
        for (size_t i = 0; i < width; ++i) sum[i] = sum[i] + beta * buf[i];
      }
      first = false;
    }
    uint8_t* d = dst + dy * int64_t(width);
    for (size_t i = 0; i < width; ++i) d[i] = saturate_u8(sum[i]);
  }
}

// ---------------------------------------------------------------- enlarging: OpenCV's bilinear stand-in

constexpr int kCoefScale = 2048;  // INTER_RESIZE_COEF_SCALE (11 bits)

// Source index and the two fixed-point weights per output index. In area mode OpenCV takes
// s = floor(d * scale) and the fraction f = (d + 1) - (s + 1) / scale, kept only when positive and reduced
// modulo 1: an output cell that lies inside one source pixel copies it, one that straddles a boundary blends.
struct LinearAxis {
  std::vector<int> src;
  std::vector<int16_t> w;  // 2 per output index
  int limit = 0;           // first output index whose right neighbour falls off the image (it copies instead)
};

LinearAxis linear_axis(int in, int out, double scale, double inv_scale) {
  LinearAxis a;
  a.src.resize(out);
  a.w.resize(size_t(out) * 2);
  a.limit = out;
  for (int d = 0; d < out; ++d) {
    int s = floor_int(d * scale);
    float f = float((d + 1) - (s + 1) * inv_scale);
    f = f <= 0 ? 0.f : f - float(floor_int(f));
    if (s + 1 >= in) {
      a.limit = std::min(a.limit, d);
      if (s >= in - 1) {
        f = 0.f;
        s = in - 1;
      }
    }
    a.src[d] = s;
    a.w[2 * d] = saturate_s16((1.f - f) * kCoefScale);
    a.w[2 * d + 1] = saturate_s16(f * kCoefScale);
  }
  return a;
}

void bilinear_area(const uint8_t* src, int in_h, int in_w, int cn, int out_h, int out_w, double scale_x,
                   double inv_x, double scale_y, double inv_y, uint8_t* dst) {
  const LinearAxis ax = linear_axis(in_w, out_w, scale_x, inv_x);
  const LinearAxis ay = linear_axis(in_h, out_h, scale_y, inv_y);
  const int64_t src_row = int64_t(in_w) * cn;
  const size_t width = size_t(out_w) * cn;

  // Horizontal pass of one source row into 32-bit sums scaled by 2048.
  auto horizontal = [&](int y, int32_t* out) {
    const uint8_t* row = src + int64_t(y) * src_row;
    for (int dx = 0; dx < out_w; ++dx) {
      const uint8_t* p = row + int64_t(ax.src[dx]) * cn;
      int32_t* o = out + size_t(dx) * cn;
      if (dx < ax.limit) {
        const int32_t w0 = ax.w[2 * dx], w1 = ax.w[2 * dx + 1];
        for (int c = 0; c < cn; ++c) o[c] = p[c] * w0 + p[c + cn] * w1;
      } else {
        for (int c = 0; c < cn; ++c) o[c] = p[c] * kCoefScale;
      }
    }
  };

  std::vector<int32_t> rows[2] = {std::vector<int32_t>(width), std::vector<int32_t>(width)};
  int cached[2] = {-1, -1};
  auto row_for = [&](int y, int slot) -> const int32_t* {
    if (cached[slot] != y) {
      const int other = 1 - slot;
      if (cached[other] == y) {
        rows[slot] = rows[other];
      } else {
        horizontal(y, rows[slot].data());
      }
      cached[slot] = y;
    }
    return rows[slot].data();
  };

  for (int dy = 0; dy < out_h; ++dy) {
    const int sy = ay.src[dy];
    const int y0 = std::clamp(sy, 0, in_h - 1), y1 = std::clamp(sy + 1, 0, in_h - 1);
    const int32_t* r0 = row_for(y0, 0);
    const int32_t* r1 = row_for(y1, 1);
    const int32_t b0 = ay.w[2 * dy], b1 = ay.w[2 * dy + 1];
    uint8_t* d = dst + dy * int64_t(width);
    for (size_t i = 0; i < width; ++i) {
      // OpenCV drops 4 bits before the 16-bit multiply and keeps its high half: not the exact
      // (b0 * r0 + b1 * r1 + 2^21) >> 22.
      const int32_t v = (((b0 * (r0[i] >> 4)) >> 16) + ((b1 * (r1[i] >> 4)) >> 16) + 2) >> 2;
      d[i] = uint8_t(std::clamp(v, 0, 255));
    }
  }
}

}  // namespace

void resize_area(const uint8_t* src, int in_h, int in_w, int channels, int out_h, int out_w, uint8_t* dst) {
  if (src == nullptr || dst == nullptr) throw Error(ErrorCode::invalid_argument, "resize_area: null buffer");
  if (in_h <= 0 || in_w <= 0 || out_h <= 0 || out_w <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_area: empty size " + std::to_string(in_h) + "x" +
                                                 std::to_string(in_w) + " -> " + std::to_string(out_h) + "x" +
                                                 std::to_string(out_w));
  if (channels < 1 || channels > 4)
    throw Error(ErrorCode::invalid_argument, "resize_area: " + std::to_string(channels) + " channels (1-4 supported)");
  if (in_h == out_h && in_w == out_w) {
    std::memcpy(dst, src, size_t(in_h) * in_w * channels);
    return;
  }
  const double inv_x = double(out_w) / in_w, inv_y = double(out_h) / in_h;
  const double scale_x = 1. / inv_x, scale_y = 1. / inv_y;
  const int kx = round_even(scale_x), ky = round_even(scale_y);
  const bool whole = std::abs(scale_x - kx) < DBL_EPSILON && std::abs(scale_y - ky) < DBL_EPSILON;
  if (scale_x >= 1 && scale_y >= 1) {
    if (whole) {
      box_average(src, in_w, channels, out_h, out_w, kx, ky, dst);
    } else {
      area_weights(src, in_h, in_w, channels, out_h, out_w, scale_x, scale_y, dst);
    }
    return;
  }
  bilinear_area(src, in_h, in_w, channels, out_h, out_w, scale_x, inv_x, scale_y, inv_y, dst);
}

Image resize_area(const Image& img, int out_h, int out_w) {
  if (img.height <= 0 || img.width <= 0 || img.rgb.size() != size_t(img.height) * img.width * 3)
    throw Error(ErrorCode::invalid_argument, "resize_area: empty or inconsistent image");
  Image out;
  out.height = out_h;
  out.width = out_w;
  if (out_h <= 0 || out_w <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_area: empty output size " + std::to_string(out_h) + "x" +
                                                 std::to_string(out_w));
  out.rgb.resize(size_t(out_h) * out_w * 3);
  resize_area(img.rgb.data(), img.height, img.width, 3, out_h, out_w, out.rgb.data());
  return out;
}

}  // namespace tether::vision
