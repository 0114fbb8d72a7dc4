// The CUDA backend's elementwise, norm, rotation, copy and sampler kernels (the hot ones: built with no local memory). Built with -fmad=false: the op tests hold
// several of these to the bit (axpy, gated_add, rtc_guide, add, scale), and the CPU backend and PyTorch's eager ops
// round every multiply and add separately. The arithmetic is element_math.h's, tested on the host.
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include "backend/cuda/element_math.h"
#include "backend/cuda/kernels.h"

namespace tether::cuda {
namespace {

namespace m = tether::cuda_math;

constexpr int kThreads = 256;

// Enough blocks for n elements at kThreads each, capped so grid-stride loops cover the rest.
unsigned grid_for(int64_t n) {
  const int64_t blocks = (n + kThreads - 1) / kThreads;
  return unsigned(blocks < 1 ? 1 : (blocks > 65535 * 8 ? 65535 * 8 : blocks));
}

// Sum of one double per thread over the block, in a fixed tree (the same bits on every run).
__device__ double block_sum(double v, double* shared) {
  shared[threadIdx.x] = v;
  __syncthreads();
  for (int width = kThreads / 2; width > 0; width /= 2) {
    if (threadIdx.x < width) shared[threadIdx.x] += shared[threadIdx.x + width];
    __syncthreads();
  }
  const double total = shared[0];
  __syncthreads();
  return total;
}

__global__ void layer_norm_kernel(const float* x, int64_t n, const float* gamma, const float* beta, float eps,
                                  float* y) {
  __shared__ double shared[kThreads];
  const float* xr = x + blockIdx.x * n;
  float* yr = y + blockIdx.x * n;
  double sum = 0;
  for (int64_t i = threadIdx.x; i < n; i += kThreads) sum += double(xr[i]);
  const double mean = block_sum(sum, shared) / double(n);
  double squares = 0;
  for (int64_t i = threadIdx.x; i < n; i += kThreads) {
    const double d = double(xr[i]) - mean;
    squares += d * d;
  }
  const m::LayerNormStats stats = m::layer_norm_stats(mean, block_sum(squares, shared), n, eps);
  for (int64_t i = threadIdx.x; i < n; i += kThreads) yr[i] = m::layer_norm_apply(xr[i], stats, gamma, beta, i);
}

__global__ void rms_norm_kernel(const float* x, int64_t n, const float* weight, int kind, float eps, float* y,
                                const float* scale, const float* shift, int64_t mod_stride, int64_t rows_per_group) {
  __shared__ double shared[kThreads];
  const float* xr = x + blockIdx.x * n;
  float* yr = y + blockIdx.x * n;
  double squares = 0;
  for (int64_t i = threadIdx.x; i < n; i += kThreads) squares += double(xr[i]) * double(xr[i]);
  const float inv = m::rms_inverse(block_sum(squares, shared), n, eps);
  const int64_t group = int64_t(blockIdx.x) / rows_per_group;
  for (int64_t i = threadIdx.x; i < n; i += kThreads) {
    float v = m::rms_apply(xr[i], inv, weight ? weight[i] : 0.0f, kind);
    if (scale) v = m::modulate(v, scale[group * mod_stride + i], shift[group * mod_stride + i]);
    yr[i] = v;
  }
}

__global__ void modulate_kernel(float* y, int64_t rows, int64_t n, const float* scale, const float* shift,
                                int64_t mod_stride, int64_t rows_per_group) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < rows * n; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t r = e / n, i = e % n, g = (r / rows_per_group) * mod_stride;
    y[e] = m::modulate(y[e], scale[g + i], shift[g + i]);
  }
}

__global__ void rope_rotate_kernel(float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cos,
                                   const float* sin) {
  const int64_t half = head_dim / 2;
  const int64_t total = rows * heads * half;
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < total; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t i = e % half, r = e / (half * heads);
    float* pair = x + (e / half) * head_dim + i;
    m::rotate_pair(pair[0], pair[half], cos[r * half + i], sin[r * half + i]);
  }
}

template <m::Act A>
__global__ void activate_kernel(float* x, int64_t n) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < n; e += int64_t(gridDim.x) * blockDim.x)
    x[e] = m::activate(A, x[e]);
}

template <m::Act A>
__global__ void gated_kernel(const float* gate_up, int64_t rows, int64_t n, float* out) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < rows * n; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t r = e / n, i = e % n;
    const float* row = gate_up + r * 2 * n;
    out[e] = m::gated(A, row[i], row[n + i]);
  }
}

__global__ void add_kernel(const float* a, const float* b, int64_t n, float* out) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < n; e += int64_t(gridDim.x) * blockDim.x)
    out[e] = a[e] + b[e];
}

__global__ void scale_kernel(float* x, int64_t n, float s) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < n; e += int64_t(gridDim.x) * blockDim.x)
    x[e] = x[e] * s;
}

__global__ void gated_add_kernel(float* x, const float* y, const float* gate, int64_t gate_stride, int64_t rows,
                                 int64_t n, int64_t rows_per_group) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < rows * n; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t r = e / n, i = e % n;
    x[e] = x[e] + y[e] * gate[(r / rows_per_group) * gate_stride + i];
  }
}

__global__ void copy_rows_kernel(const float* src, int64_t src_stride, float* dst, int64_t dst_stride, int64_t rows,
                                 int64_t width) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < rows * width;
       e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t r = e / width, i = e % width;
    dst[r * dst_stride + i] = src[r * src_stride + i];
  }
}

__global__ void gather_rows_kernel(const void* table, int type, int64_t width, const int64_t* ids, int64_t count,
                                   float scale, float* out, int64_t ldo) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < count * width;
       e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t r = e / width, i = e % width, at = ids[r] * width + i;
    float v;
    if (type == int(StoredType::bf16)) v = m::bf16_bits_to_float(static_cast<const uint16_t*>(table)[at]);
    else if (type == int(StoredType::f16)) v = m::f16_bits_to_float(static_cast<const uint16_t*>(table)[at]);
    else v = static_cast<const float*>(table)[at];
    // A scale of one leaves the row as stored (the CPU backend skips the multiply then).
    out[r * ldo + i] = scale == 1.0f ? v : v * scale;
  }
}

__global__ void im2col_kernel(const float* pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                              int64_t patch, float* cols) {
  const int64_t pw = width / patch, patches = (height / patch) * pw, col_len = channels * patch * patch;
  const int64_t total = batch * patches * col_len;
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < total; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t b = e / (patches * col_len), p = (e / col_len) % patches, j = e % col_len;
    const int64_t c = j / (patch * patch), ky = (j / patch) % patch, kx = j % patch;
    const int64_t py = p / pw, px = p % pw;
    cols[e] = pixels[((b * channels + c) * height + py * patch + ky) * width + px * patch + kx];
  }
}

__global__ void pixel_shuffle_kernel(const float* x, int64_t batch, int64_t seq, int64_t side, int64_t embed,
                                     int64_t ratio, float* out) {
  const int64_t out_side = side / ratio, out_seq = out_side * out_side, out_embed = embed * ratio * ratio;
  const int64_t total = batch * out_seq * out_embed;
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < total; e += int64_t(gridDim.x) * blockDim.x) {
    const int64_t t = e / out_embed, f = e % out_embed;
    const int64_t b = t / out_seq, i2 = (t % out_seq) / out_side, j2 = t % out_side;
    const int64_t a = f / (ratio * embed), c = (f / embed) % ratio, d = f % embed;
    const int64_t src_token = (i2 * ratio + a) * side + (j2 * ratio + c);
    out[e] = x[(b * seq + src_token) * embed + d];
  }
}

__global__ void axpy_kernel(float* x, const float* v, int64_t n, float a) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < n; e += int64_t(gridDim.x) * blockDim.x)
    x[e] = m::axpy(x[e], a, v[e]);
}

__global__ void rtc_guide_kernel(const float* x, float* v, const float* target, const float* weights, int64_t chunk,
                                 int64_t width, float time, float guidance_weight) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < chunk * width;
       e += int64_t(gridDim.x) * blockDim.x)
    v[e] = m::rtc_guide(x[e], v[e], target[e], weights[e / width], time, guidance_weight);
}

// One block: a chunk is a few thousand elements.
__global__ void change_norms_kernel(const float* v, const float* prev, int64_t chunk, int64_t width,
                                    int64_t action_dim, double* sums) {
  __shared__ double shared[kThreads];
  double diff = 0, norm = 0;
  for (int64_t e = threadIdx.x; e < chunk * action_dim; e += kThreads) {
    const int64_t i = (e / action_dim) * width + e % action_dim;
    const double d = double(v[i]) - double(prev[i]);
    diff += d * d;
    norm += double(prev[i]) * double(prev[i]);
  }
  diff = block_sum(diff, shared);
  norm = block_sum(norm, shared);
  if (threadIdx.x == 0) sums[0] = diff, sums[1] = norm;
}

__global__ void convert_kernel(const float* x, int64_t n, int type, uint16_t* out) {
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < n; e += int64_t(gridDim.x) * blockDim.x)
    out[e] = type == int(StoredType::bf16) ? m::float_to_bf16_bits(x[e]) : __half_as_ushort(__float2half_rn(x[e]));
}

template <template <m::Act> class Launch, typename... Args>
void with_activation(int act, Args... args) {
  switch (m::Act(act)) {
    case m::Act::silu: Launch<m::Act::silu>::run(args...); return;
    case m::Act::gelu_tanh: Launch<m::Act::gelu_tanh>::run(args...); return;
    case m::Act::gelu_erf: Launch<m::Act::gelu_erf>::run(args...); return;
    case m::Act::relu: Launch<m::Act::relu>::run(args...); return;
  }
}

template <m::Act A>
struct LaunchActivate {
  static void run(cudaStream_t s, float* x, int64_t n) { activate_kernel<A><<<grid_for(n), kThreads, 0, s>>>(x, n); }
};
template <m::Act A>
struct LaunchGated {
  static void run(cudaStream_t s, const float* gu, int64_t rows, int64_t n, float* out) {
    gated_kernel<A><<<grid_for(rows * n), kThreads, 0, s>>>(gu, rows, n, out);
  }
};

}  // namespace

bool kernels_loadable(std::string* why) {
  cudaFuncAttributes attributes{};
  const cudaError_t status = cudaFuncGetAttributes(&attributes, axpy_kernel);
  if (status == cudaSuccess) return true;
  cudaGetLastError();
  int device = 0, major = 0, minor = 0;
  cudaGetDevice(&device);
  cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device);
  cudaDeviceGetAttribute(&minor, cudaDevAttrComputeCapabilityMinor, device);
  if (why)
    *why = "this build has no code for the GPU's compute capability " + std::to_string(major) + "." +
           std::to_string(minor) + " (built for " TETHER_CUDA_TARGETS "): " + cudaGetErrorString(status);
  return false;
}

void layer_norm(cudaStream_t s, const float* x, int64_t rows, int64_t n, const float* gamma, const float* beta,
                float eps, float* y) {
  if (rows > 0) layer_norm_kernel<<<unsigned(rows), kThreads, 0, s>>>(x, n, gamma, beta, eps, y);
}

void rms_norm(cudaStream_t s, const float* x, int64_t rows, int64_t n, const float* weight, int kind, float eps,
              float* y, const float* scale, const float* shift, int64_t mod_stride, int64_t rows_per_group) {
  if (rows > 0)
    rms_norm_kernel<<<unsigned(rows), kThreads, 0, s>>>(x, n, weight, kind, eps, y, scale, shift, mod_stride,
                                                         rows_per_group);
}

void modulate(cudaStream_t s, float* y, int64_t rows, int64_t n, const float* scale, const float* shift,
              int64_t mod_stride, int64_t rows_per_group) {
  if (rows * n > 0)
    modulate_kernel<<<grid_for(rows * n), kThreads, 0, s>>>(y, rows, n, scale, shift, mod_stride, rows_per_group);
}

void rope_rotate(cudaStream_t s, float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cos,
                 const float* sin) {
  const int64_t total = rows * heads * (head_dim / 2);
  if (total > 0) rope_rotate_kernel<<<grid_for(total), kThreads, 0, s>>>(x, rows, heads, head_dim, cos, sin);
}

void activate(cudaStream_t s, float* x, int64_t n, int act) {
  if (n > 0) with_activation<LaunchActivate>(act, s, x, n);
}

void gated(cudaStream_t s, const float* gate_up, int64_t rows, int64_t n, int act, float* out) {
  if (rows * n > 0) with_activation<LaunchGated>(act, s, gate_up, rows, n, out);
}

void add(cudaStream_t s, const float* a, const float* b, int64_t n, float* out) {
  if (n > 0) add_kernel<<<grid_for(n), kThreads, 0, s>>>(a, b, n, out);
}

void scale(cudaStream_t s, float* x, int64_t n, float factor) {
  if (n > 0) scale_kernel<<<grid_for(n), kThreads, 0, s>>>(x, n, factor);
}

void gated_add(cudaStream_t s, float* x, const float* y, const float* gate, int64_t gate_stride, int64_t rows,
               int64_t n, int64_t rows_per_group) {
  if (rows * n > 0)
    gated_add_kernel<<<grid_for(rows * n), kThreads, 0, s>>>(x, y, gate, gate_stride, rows, n, rows_per_group);
}

void copy_rows(cudaStream_t s, const float* src, int64_t src_stride, float* dst, int64_t dst_stride, int64_t rows,
               int64_t width) {
  if (rows * width > 0)
    copy_rows_kernel<<<grid_for(rows * width), kThreads, 0, s>>>(src, src_stride, dst, dst_stride, rows, width);
}

void gather_rows(cudaStream_t s, const void* table, StoredType type, int64_t width, const int64_t* ids, int64_t count,
                 float factor, float* out, int64_t ldo) {
  if (count * width > 0)
    gather_rows_kernel<<<grid_for(count * width), kThreads, 0, s>>>(table, int(type), width, ids, count, factor, out,
                                                                     ldo);
}

void im2col_patches(cudaStream_t s, const float* pixels, int64_t batch, int64_t channels, int64_t height,
                    int64_t width, int64_t patch, float* cols) {
  const int64_t total = batch * channels * height * width;
  if (total > 0) im2col_kernel<<<grid_for(total), kThreads, 0, s>>>(pixels, batch, channels, height, width, patch, cols);
}

void pixel_shuffle(cudaStream_t s, const float* x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                   float* out) {
  int64_t side = 0;
  while ((side + 1) * (side + 1) <= seq) ++side;
  const int64_t total = batch * seq * embed;
  if (total > 0) pixel_shuffle_kernel<<<grid_for(total), kThreads, 0, s>>>(x, batch, seq, side, embed, ratio, out);
}

void axpy(cudaStream_t s, float* x, const float* v, int64_t n, float a) {
  if (n > 0) axpy_kernel<<<grid_for(n), kThreads, 0, s>>>(x, v, n, a);
}

void rtc_guide(cudaStream_t s, const float* x, float* v, const float* target, const float* weights, int64_t chunk,
               int64_t width, float time, float guidance_weight) {
  if (chunk * width > 0)
    rtc_guide_kernel<<<grid_for(chunk * width), kThreads, 0, s>>>(x, v, target, weights, chunk, width, time,
                                                                   guidance_weight);
}

void change_norms(cudaStream_t s, const float* v, const float* prev, int64_t chunk, int64_t width, int64_t action_dim,
                  double* sums) {
  change_norms_kernel<<<1, kThreads, 0, s>>>(v, prev, chunk, width, action_dim, sums);
}

void convert_from_f32(cudaStream_t s, const float* x, int64_t n, StoredType type, void* out) {
  if (n > 0) convert_kernel<<<grid_for(n), kThreads, 0, s>>>(x, n, int(type), static_cast<uint16_t*>(out));
}

}  // namespace tether::cuda
