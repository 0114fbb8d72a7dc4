// Image preprocessing bit-exact with lerobot + torch on CPU: uint8 -> [0,1] floats, torch's
// bilinear resize (F.interpolate, align_corners=False, antialias=False, float32), lerobot's
// resize-with-pad. Everything writes into caller buffers and allocates nothing once warmed
// (per-thread index tables).
#pragma once

#include "vision/image.h"

namespace tether::vision {

// torch runs one of two float32 CPU bilinear kernels and they round differently in the last bit:
// a separable one (used when torch has several threads and out_h + out_w > 128) and a four-tap one
// (used when out_h + out_w <= 128, or for 3-channel images when torch runs on a single thread).
// Matching the reference bit for bit therefore needs to know how many threads it ran with.
enum class TorchThreads { many, one };

// The kernel torch would pick (see above); exposed for tests.
enum class BilinearKernel { separable, four_tap };
BilinearKernel torch_bilinear_kernel(int channels, int in_h, int in_w, int out_h, int out_w,
                                     TorchThreads threads);

// HWC uint8 -> CHW float32, x / 255 (a true division, as torch does it).
void to_float_chw(const Image& img, float* out);

// torch.nn.functional.interpolate(mode="bilinear", align_corners=False, antialias=False) on a
// contiguous float32 (1, channels, in_h, in_w) tensor; `out` holds channels * out_h * out_w floats.
void resize_bilinear(const float* in, int channels, int in_h, int in_w, int out_h, int out_w,
                     float* out, TorchThreads threads = TorchThreads::many);

// The size lerobot's resize_with_pad resizes to before padding to (out_h, out_w). Throws
// invalid_argument when a side would shrink to zero pixels (torch refuses that too).
struct ResizedSize {
  int height = 0, width = 0;
};
ResizedSize resize_with_pad_size(int in_h, int in_w, int out_h, int out_w);

// lerobot policies/common/vla_utils.py::resize_with_pad (SmolVLA's variant): aspect-preserving
// bilinear resize, then padding with `pad_value` on the LEFT and TOP. Same size: copied unchanged.
void resize_with_pad(const float* in, int channels, int in_h, int in_w, int out_h, int out_w,
                     float pad_value, float* out, TorchThreads threads = TorchThreads::many);

// Where [0, 1] pixels land after resizing: y * (hi - lo) + lo. SmolVLA (and pi0) use [-1, 1].
struct PixelRange {
  float lo = -1.0f, hi = 1.0f;
};

// Where the padding goes: SmolVLA's resize_with_pad pads the top and left; openpi's resize_with_pad_torch (pi0,
// pi0.5) centres the image, the odd pixel of padding going to the bottom / right, and clamps the resized values to
// [0, 1] before padding.
enum class PadPlacement { top_left, centred };

// One camera as the lerobot VLA policies prepare it: x / 255, resize_with_pad(pad_value) to (out_h, out_w), then
// mapped to `range`, so with the defaults padded pixels end as -1. `out` holds 3 * out_h * out_w floats (CHW).
// Note the SmolVLA config stores resize_imgs_with_padding as (width, height).
void resize_with_pad_normalized(const Image& img, int out_h, int out_w, float* out,
                                TorchThreads threads = TorchThreads::many, PixelRange range = {},
                                float pad_value = 0.0f, PadPlacement placement = PadPlacement::top_left);

namespace detail {
// Tests only: run the portable kernel build (libm fma) even on a CPU with FMA instructions, to
// check that both builds give identical bits. Not meant to be toggled while other threads
// preprocess.
void force_portable_kernels(bool on);
}  // namespace detail

}  // namespace tether::vision
