// Kernels that evaluate sin, cos and pow of arbitrary arguments: the rotary angles of each position and the flow
// sampler's time embedding. CUDA's large-argument reduction for these keeps a small array in local memory, so they
// live apart from the hot kernels, which are held to none (cmake/cuda.cmake); each runs once per forward pass or
// denoise step on a few thousand values. Built without FMA contraction, like the CPU backend.
#include <algorithm>

#include "backend/cuda/element_math.h"
#include "backend/cuda/kernels.h"

namespace tether::cuda {
namespace {

namespace m = tether::cuda_math;

constexpr int kThreads = 256;

__global__ void rope_angles_kernel(const int64_t* positions, int64_t tokens, int64_t head_dim, float max_wavelength,
                                   int angles, float* cos_out, float* sin_out) {
  const int64_t half = head_dim / 2;
  for (int64_t e = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; e < tokens * half;
       e += int64_t(gridDim.x) * blockDim.x) {
    const float timescale = m::rope_timescale(e % half, head_dim, max_wavelength, angles);
    const float radians = m::rope_angle(float(positions[e / half]), timescale, angles);
    cos_out[e] = cosf(radians);
    sin_out[e] = sinf(radians);
  }
}

__global__ void time_embedding_kernel(double time, int64_t half, double min_period, double max_period, float* out) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i < half) m::time_embedding_pair(time, i, half, min_period, max_period, out[i], out[half + i]);
}

unsigned grid_for(int64_t n) { return unsigned(std::min<int64_t>((n + kThreads - 1) / kThreads, 4096)); }

}  // namespace

void rope_angles(cudaStream_t s, const int64_t* positions, int64_t tokens, int64_t head_dim, float max_wavelength,
                 int angles, float* cos, float* sin) {
  const int64_t total = tokens * (head_dim / 2);
  if (total > 0)
    rope_angles_kernel<<<grid_for(total), kThreads, 0, s>>>(positions, tokens, head_dim, max_wavelength, angles, cos,
                                                             sin);
}

void time_embedding(cudaStream_t s, double time, int64_t dim, double min_period, double max_period, float* out) {
  const int64_t half = dim / 2;
  if (half > 0) time_embedding_kernel<<<grid_for(half), kThreads, 0, s>>>(time, half, min_period, max_period, out);
}

}  // namespace tether::cuda
