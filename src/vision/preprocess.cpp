// Bilinear resize and resize-with-pad preprocessing, reproducing torch's float32 CPU kernels bit for bit.
//
// What torch computes (aten/src/ATen/native/UpSample.h and cpu/UpSampleKernel.cpp), per axis:
//   scale = float(in) / float(out)                     (float32 division)
//   src   = fma(scale, float(o) + 0.5f, -0.5f)         (x86 builds contract this into one FMA)
//   src   = max(src, 0);  i0 = min(int(src), in - 1);  i1 = i0 + (i0 < in - 1)
//   l1    = clamp(src - i0, 0, 1);  l0 = 1 - l1
//   (and in == out gives i0 = i1 = o, l0 = 1, l1 = 0).
// Then one of two kernels (see TorchThreads in preprocess.h), with these exact fusions:
//   separable: t0 = fma(x00, w0, x01 * w1); t1 = fma(x10, w0, x11 * w1); y = fma(t0, h0, t1 * h1)
//   four-tap:  y = fma(x11, h1*w1, fma(x10, h1*w0, fma(x00, h0*w0, x01 * (h0*w1))))
// The fusions were confirmed against torch 2.11 (AVX-512 dispatch) on many sizes; torch's
// non-FMA fallback build would round differently. The four-tap form is torch's per-channel tail
// loop, which is what runs for images (3 channels, below the SIMD width); at 8+ channels torch
// sums in a different order and this kernel can differ from it in the last bit.
#include "vision/preprocess.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include "core/error.h"

namespace tether::vision {

namespace {

// Per-axis source indices and weights, rebuilt per call into storage that only ever grows, so a
// warmed-up thread preprocesses without touching the allocator.
struct AxisTable {
  std::vector<int32_t> i0, i1;
  std::vector<float> l0, l1;

  void build(int in, int out) {
    if (int(i0.size()) < out) {
      i0.resize(out);
      i1.resize(out);
      l0.resize(out);
      l1.resize(out);
    }
    if (in == out) {
      for (int o = 0; o < out; ++o) {
        i0[o] = i1[o] = o;
        l0[o] = 1.0f;
        l1[o] = 0.0f;
      }
      return;
    }
    const float scale = float(in) / float(out);
    for (int o = 0; o < out; ++o) {
      float src = std::fma(scale, float(o) + 0.5f, -0.5f);
      if (src < 0.0f) src = 0.0f;
      const int idx = std::min(int(src), in - 1);
      const float lambda1 = std::min(std::max(src - float(idx), 0.0f), 1.0f);
      i0[o] = idx;
      i1[o] = idx + (idx < in - 1 ? 1 : 0);
      l1[o] = lambda1;
      l0[o] = 1.0f - lambda1;
    }
  }
};

thread_local AxisTable t_rows, t_cols;

// x / 255 for every byte, as torch's float32 true division yields it.
struct U8Lut {
  float v[256];
  U8Lut() {
    for (int i = 0; i < 256; ++i) v[i] = float(i) / 255.0f;
  }
};
const U8Lut kLut;

// Where the kernels read from: float CHW planes, or the decoded uint8 HWC image with the /255
// folded in (identical values, and no intermediate float image).
struct PlanarF32 {
  const float* data;
  int64_t plane;
  int width;
  const float* row(int c, int y) const { return data + c * plane + int64_t(y) * width; }
  static float at(const float* row, int x) { return row[x]; }
};

struct InterleavedU8 {
  const uint8_t* data;
  int width;
  const uint8_t* row(int c, int y) const { return data + (int64_t(y) * width) * 3 + c; }
  static float at(const uint8_t* row, int x) { return kLut.v[row[3 * x]]; }
};

struct Job {
  int channels, out_h, out_w;   // size of the resized region
  float* out;                   // (channels, dst_h, dst_w)
  int dst_h, dst_w, top, left;  // the region's placement inside `out`
  bool affine;                  // store y * scale + offset instead of y
  BilinearKernel kernel;
  float scale = 1.0f, offset = 0.0f;
  bool clamp01 = false;  // clamp the interpolated value to [0, 1] first (openpi's centred variant does)
};

inline float finish(float y, const Job& j) {
  if (j.clamp01) y = std::min(std::max(y, 0.0f), 1.0f);
  return j.affine ? y * j.scale + j.offset : y;
}

template <class Src>
[[gnu::always_inline]] inline void run_separable(const Src& src, const Job& j) {
  const AxisTable& r = t_rows;
  const AxisTable& k = t_cols;
  for (int c = 0; c < j.channels; ++c) {
    for (int oy = 0; oy < j.out_h; ++oy) {
      const auto* row0 = src.row(c, r.i0[oy]);
      const auto* row1 = src.row(c, r.i1[oy]);
      const float h0 = r.l0[oy], h1 = r.l1[oy];
      float* o = j.out + (int64_t(c) * j.dst_h + oy + j.top) * j.dst_w + j.left;
      for (int ox = 0; ox < j.out_w; ++ox) {
        const int a = k.i0[ox], b = k.i1[ox];
        const float w0 = k.l0[ox], w1 = k.l1[ox];
        const float t0 = std::fma(Src::at(row0, a), w0, Src::at(row0, b) * w1);
        const float t1 = std::fma(Src::at(row1, a), w0, Src::at(row1, b) * w1);
        o[ox] = finish(std::fma(t0, h0, t1 * h1), j);
      }
    }
  }
}

template <class Src>
[[gnu::always_inline]] inline void run_four_tap(const Src& src, const Job& j) {
  const AxisTable& r = t_rows;
  const AxisTable& k = t_cols;
  for (int c = 0; c < j.channels; ++c) {
    for (int oy = 0; oy < j.out_h; ++oy) {
      const auto* row0 = src.row(c, r.i0[oy]);
      const auto* row1 = src.row(c, r.i1[oy]);
      const float h0 = r.l0[oy], h1 = r.l1[oy];
      float* o = j.out + (int64_t(c) * j.dst_h + oy + j.top) * j.dst_w + j.left;
      for (int ox = 0; ox < j.out_w; ++ox) {
        const int a = k.i0[ox], b = k.i1[ox];
        const float w0 = k.l0[ox], w1 = k.l1[ox];
        const float w00 = h0 * w0, w01 = h0 * w1, w10 = h1 * w0, w11 = h1 * w1;
        float y = std::fma(Src::at(row0, a), w00, Src::at(row0, b) * w01);
        y = std::fma(Src::at(row1, a), w10, y);
        y = std::fma(Src::at(row1, b), w11, y);
        o[ox] = finish(y, j);
      }
    }
  }
}

template <class Src>
[[gnu::always_inline]] inline void run(const Src& src, const Job& j) {
  if (j.kernel == BilinearKernel::separable) {
    run_separable(src, j);
  } else {
    run_four_tap(src, j);
  }
}

void run_f32_portable(const PlanarF32& s, const Job& j) { run(s, j); }
void run_u8_portable(const InterleavedU8& s, const Job& j) { run(s, j); }

std::atomic<bool> g_force_portable{false};

#if defined(__x86_64__)
// Two builds of the kernels: one for CPUs with FMA, where std::fma is one instruction, and a
// portable one where it is a (correctly rounded, slower) libm call. Both give identical results.
[[gnu::target("avx2,fma"), gnu::flatten]] void run_f32_fma(const PlanarF32& s, const Job& j) {
  run(s, j);
}
[[gnu::target("avx2,fma"), gnu::flatten]] void run_u8_fma(const InterleavedU8& s, const Job& j) {
  run(s, j);
}

bool use_fma_kernels() {
  static const bool has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has && !g_force_portable.load(std::memory_order_relaxed);
}
#else
// AArch64's baseline has a fused multiply-add instruction, so the portable build already runs std::fma as one
// instruction: there is no second build to pick.
void run_f32_fma(const PlanarF32& s, const Job& j) { run_f32_portable(s, j); }
void run_u8_fma(const InterleavedU8& s, const Job& j) { run_u8_portable(s, j); }
bool use_fma_kernels() { return false; }
#endif

template <class Src>
void run_dispatch(const Src& src, const Job& j) {
  if constexpr (std::is_same_v<Src, PlanarF32>) {
    use_fma_kernels() ? run_f32_fma(src, j) : run_f32_portable(src, j);
  } else {
    use_fma_kernels() ? run_u8_fma(src, j) : run_u8_portable(src, j);
  }
}

void check_size(const char* what, int h, int w) {
  if (h <= 0 || w <= 0)
    throw Error(ErrorCode::invalid_argument, std::string(what) + " size " + std::to_string(h) +
                                                 "x" + std::to_string(w) + " is not positive");
}

void check_ptr(const void* p, const char* what) {
  if (p == nullptr) throw Error(ErrorCode::invalid_argument, std::string(what) + " buffer is null");
}

// Fills everything of each (dst_h, dst_w) plane outside the resized region (h, w) placed at (top, left).
void fill_padding(float* out, int channels, int dst_h, int dst_w, int top, int left, int h, int w, float value) {
  for (int c = 0; c < channels; ++c) {
    float* plane = out + int64_t(c) * dst_h * dst_w;
    std::fill(plane, plane + int64_t(top) * dst_w, value);
    for (int y = top; y < top + h; ++y) {
      std::fill_n(plane + int64_t(y) * dst_w, left, value);
      std::fill(plane + int64_t(y) * dst_w + left + w, plane + int64_t(y + 1) * dst_w, value);
    }
    std::fill(plane + int64_t(top + h) * dst_w, plane + int64_t(dst_h) * dst_w, value);
  }
}

struct Placement {
  int top = 0, left = 0;
};
// Where the resized region sits: bottom-right (padding on the top and left) or centred, the extra pixel of an odd
// padding going to the bottom / right (Python's divmod, as openpi writes it).
Placement place(ResizedSize r, int out_h, int out_w, PadPlacement where) {
  const int pad_h = std::max(0, out_h - r.height), pad_w = std::max(0, out_w - r.width);
  if (where == PadPlacement::top_left) return {pad_h, pad_w};
  return {pad_h / 2, pad_w / 2};
}

void check_image(const Image& img) {
  check_size("image", img.height, img.width);
  if (img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3)
    throw Error(ErrorCode::invalid_argument,
                "image buffer holds " + std::to_string(img.rgb.size()) + " bytes, expected " +
                    std::to_string(img.height) + "x" + std::to_string(img.width) + "x3");
}

}  // namespace

namespace detail {
void force_portable_kernels(bool on) { g_force_portable.store(on, std::memory_order_relaxed); }
}  // namespace detail

BilinearKernel torch_bilinear_kernel(int channels, int in_h, int in_w, int out_h, int out_w,
                                     TorchThreads threads) {
  // torch takes the four-tap (channels-last) kernel when the input is channels-last contiguous with
  // more than 3 channels (a contiguous NCHW tensor only is when it has one pixel), when the output
  // is small, or for 3-channel images on one thread.
  const bool channels_last_input = channels > 3 && in_h == 1 && in_w == 1;
  if (channels_last_input || out_h + out_w <= 128 ||
      (threads == TorchThreads::one && channels == 3))
    return BilinearKernel::four_tap;
  return BilinearKernel::separable;
}

void to_float_chw(const Image& img, float* out) {
  check_image(img);
  check_ptr(out, "output");
  const int64_t n = int64_t(img.height) * img.width;
  const uint8_t* p = img.rgb.data();
  for (int c = 0; c < 3; ++c)
    for (int64_t i = 0; i < n; ++i) out[c * n + i] = kLut.v[p[i * 3 + c]];
}

void resize_bilinear(const float* in, int channels, int in_h, int in_w, int out_h, int out_w,
                     float* out, TorchThreads threads) {
  check_ptr(in, "input");
  check_ptr(out, "output");
  if (channels <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_bilinear: channels must be positive");
  check_size("resize_bilinear input", in_h, in_w);
  check_size("resize_bilinear output", out_h, out_w);
  t_rows.build(in_h, out_h);
  t_cols.build(in_w, out_w);
  const Job job{channels, out_h,
                out_w,    out,
                out_h,    out_w,
                0,        0,
                false,    torch_bilinear_kernel(channels, in_h, in_w, out_h, out_w, threads)};
  run_dispatch(PlanarF32{in, int64_t(in_h) * in_w, in_w}, job);
}

ResizedSize resize_with_pad_size(int in_h, int in_w, int out_h, int out_w) {
  check_size("resize_with_pad input", in_h, in_w);
  check_size("resize_with_pad target", out_h, out_w);
  // Python float (double) division then int() truncation, exactly as lerobot writes it.
  const double ratio = std::max(double(in_w) / out_w, double(in_h) / out_h);
  const ResizedSize r{int(double(in_h) / ratio), int(double(in_w) / ratio)};
  if (r.height <= 0 || r.width <= 0)
    throw Error(ErrorCode::invalid_argument,
                "image " + std::to_string(in_h) + "x" + std::to_string(in_w) + " resized into " +
                    std::to_string(out_h) + "x" + std::to_string(out_w) +
                    " keeping its aspect ratio would be " + std::to_string(r.height) + "x" +
                    std::to_string(r.width) + " (a side of zero pixels)");
  return r;
}

void resize_with_pad(const float* in, int channels, int in_h, int in_w, int out_h, int out_w,
                     float pad_value, float* out, TorchThreads threads) {
  check_ptr(in, "input");
  check_ptr(out, "output");
  if (channels <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_with_pad: channels must be positive");
  if (in_h == out_h && in_w == out_w) {
    check_size("resize_with_pad input", in_h, in_w);
    std::memcpy(out, in,
                sizeof(float) * std::size_t(channels) * std::size_t(in_h) * std::size_t(in_w));
    return;
  }
  const ResizedSize r = resize_with_pad_size(in_h, in_w, out_h, out_w);
  const auto [top, left] = place(r, out_h, out_w, PadPlacement::top_left);
  t_rows.build(in_h, r.height);
  t_cols.build(in_w, r.width);
  const Job job{channels, r.height,
                r.width,  out,
                out_h,    out_w,
                top,      left,
                false,    torch_bilinear_kernel(channels, in_h, in_w, r.height, r.width, threads)};
  run_dispatch(PlanarF32{in, int64_t(in_h) * in_w, in_w}, job);
  fill_padding(out, channels, out_h, out_w, top, left, r.height, r.width, pad_value);
}

void resize_with_pad_normalized(const Image& img, int out_h, int out_w, float* out, TorchThreads threads,
                                PixelRange range, float pad_value, PadPlacement placement) {
  check_image(img);
  check_ptr(out, "output");
  check_size("preprocess target", out_h, out_w);
  const float scale = range.hi - range.lo, offset = range.lo;
  const int in_h = img.height, in_w = img.width;
  if (in_h == out_h && in_w == out_w) {
    const int64_t n = int64_t(in_h) * in_w;
    const uint8_t* p = img.rgb.data();
    for (int c = 0; c < 3; ++c)
      for (int64_t i = 0; i < n; ++i) out[c * n + i] = kLut.v[p[i * 3 + c]] * scale + offset;
    return;
  }
  const ResizedSize r = resize_with_pad_size(in_h, in_w, out_h, out_w);
  const auto [top, left] = place(r, out_h, out_w, placement);
  t_rows.build(in_h, r.height);
  t_cols.build(in_w, r.width);
  Job job{3,       r.height,
          r.width, out,
          out_h,   out_w,
          top,     left,
          true,    torch_bilinear_kernel(3, in_h, in_w, r.height, r.width, threads)};
  job.scale = scale;
  job.offset = offset;
  job.clamp01 = placement == PadPlacement::centred;
  run_dispatch(InterleavedU8{img.rgb.data(), in_w}, job);
  // Padding goes through the same map as the pixels (0 -> -1 for [-1, 1]).
  fill_padding(out, 3, out_h, out_w, top, left, r.height, r.width, pad_value * scale + offset);
}

}  // namespace tether::vision
