// Masked grouped-query attention as one fused (flash-style) kernel in float32: each block holds 16 (or 8) query rows of one
// (item, head) on chip, streams the keys and values through shared memory 32 at a time, and keeps a running softmax
// per row (element_math.h's OnlineSoftmax), so the score matrix never reaches global memory. Lanes split the keys
// for the scores and the head dimensions for the weighted sum. Scores round like the CPU backend's (the scale
// multiplies the finished dot product; masked keys score the lowest float).
#include <cfloat>

#include "backend/cuda/element_math.h"
#include "backend/cuda/kernels.h"

namespace tether::cuda {
namespace {

namespace m = tether::cuda_math;

constexpr int kWarps = 4;
constexpr int kKeyTile = 32;
// Query rows per warp: four, or two where each lane holds six or more dimensions (the registers would spill).
template <int DimsPerLane>
constexpr int kRowsPerWarp = DimsPerLane >= 6 ? 2 : 4;
template <int DimsPerLane>
constexpr int kRowsPerBlock = kWarps * kRowsPerWarp<DimsPerLane>;

__device__ __forceinline__ float warp_max(float v) {
  for (int offset = 16; offset > 0; offset /= 2) v = fmaxf(v, __shfl_xor_sync(0xffffffffu, v, offset));
  return v;
}

__device__ __forceinline__ float warp_sum(float v) {
  for (int offset = 16; offset > 0; offset /= 2) v += __shfl_xor_sync(0xffffffffu, v, offset);
  return v;
}

constexpr size_t shared_bytes(int rows_per_block, int64_t head_dim) {
  return sizeof(float) * size_t(rows_per_block * head_dim + kKeyTile * (head_dim + 1) + kKeyTile * head_dim);
}

// DimsPerLane = ceil(head_dim / 32): each lane owns head dimensions lane, lane + 32, ... of the output.
template <int DimsPerLane, int kRowsPerWarp = kRowsPerWarp<DimsPerLane>,
          int kRowsPerBlock = kRowsPerBlock<DimsPerLane>>
__global__ void __launch_bounds__(kWarps * 32, 1)
    attention_kernel(const float* __restrict__ q, int64_t q_stride, const float* __restrict__ k,
                     const float* __restrict__ v, int64_t kv_stride, const uint8_t* __restrict__ mask, int64_t len_q,
                     int64_t len_k, int64_t heads, int64_t kv_heads, int head_dim, float scale,
                     float* __restrict__ out) {
  extern __shared__ float shared[];
  float* q_tile = shared;                                   // [kRowsPerBlock][head_dim]
  float* k_tile = q_tile + kRowsPerBlock * head_dim;        // [kKeyTile][head_dim + 1]: lanes read rows, no conflicts
  float* v_tile = k_tile + kKeyTile * (head_dim + 1);       // [kKeyTile][head_dim]
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  const int64_t b = blockIdx.z, h = blockIdx.y, row0 = int64_t(blockIdx.x) * kRowsPerBlock;
  const int64_t kh = h / (heads / kv_heads);

  for (int e = threadIdx.x; e < kRowsPerBlock * head_dim; e += blockDim.x) {
    const int64_t r = row0 + e / head_dim;
    q_tile[e] = r < len_q ? q[(b * len_q + r) * q_stride + h * head_dim + e % head_dim] : 0.0f;
  }

  m::OnlineSoftmax state[kRowsPerWarp];
  float acc[kRowsPerWarp][DimsPerLane];
#pragma unroll
  for (int r = 0; r < kRowsPerWarp; ++r) {
    state[r] = m::online_softmax_start();
#pragma unroll
    for (int t = 0; t < DimsPerLane; ++t) acc[r][t] = 0.0f;
  }

  for (int64_t key0 = 0; key0 < len_k; key0 += kKeyTile) {
    __syncthreads();  // the previous tile is consumed (and, the first time, q_tile is written)
    for (int e = threadIdx.x; e < kKeyTile * head_dim; e += blockDim.x) {
      const int64_t j = key0 + e / head_dim;
      const int d = e % head_dim;
      const int64_t at = (b * len_k + j) * kv_stride + kh * head_dim + d;
      k_tile[(e / head_dim) * (head_dim + 1) + d] = j < len_k ? k[at] : 0.0f;
      v_tile[e] = j < len_k ? v[at] : 0.0f;
    }
    __syncthreads();
    const int64_t key = key0 + lane;
    const bool in_range = key < len_k;
#pragma unroll
    for (int r = 0; r < kRowsPerWarp; ++r) {
      const int local_row = warp * kRowsPerWarp + r;
      const int64_t row = row0 + local_row;
      if (row >= len_q) continue;  // the same for every lane of the warp
      const float* qr = q_tile + local_row * head_dim;
      const float* kr = k_tile + lane * (head_dim + 1);
      float dot = 0.0f;
      for (int d = 0; d < head_dim; ++d) dot += qr[d] * kr[d];
      const bool keep = in_range && (!mask || mask[(b * len_q + row) * len_k + key]);
      const float score = in_range ? m::masked_score(dot, scale, keep) : -INFINITY;
      const float factor = m::online_softmax_rescale(state[r], warp_max(score));
      const float p = in_range ? m::online_softmax_weight(state[r], score) : 0.0f;
      state[r].sum += warp_sum(p);
#pragma unroll
      for (int t = 0; t < DimsPerLane; ++t) acc[r][t] *= factor;
      for (int j = 0; j < kKeyTile; ++j) {
        const float pj = __shfl_sync(0xffffffffu, p, j);
        const float* vr = v_tile + j * head_dim;
#pragma unroll
        for (int t = 0; t < DimsPerLane; ++t) {
          const int d = lane + 32 * t;
          if (d < head_dim) acc[r][t] += pj * vr[d];
        }
      }
    }
  }

#pragma unroll
  for (int r = 0; r < kRowsPerWarp; ++r) {
    const int64_t row = row0 + warp * kRowsPerWarp + r;
    if (row >= len_q) continue;
    const float inv = 1.0f / state[r].sum;
    float* o = out + (b * len_q + row) * heads * head_dim + h * head_dim;
#pragma unroll
    for (int t = 0; t < DimsPerLane; ++t) {
      const int d = lane + 32 * t;
      if (d < head_dim) o[d] = acc[r][t] * inv;
    }
  }
}

template <int DimsPerLane>
void launch(cudaStream_t stream, const float* q, int64_t q_stride, const float* k, const float* v, int64_t kv_stride,
            const uint8_t* mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
            int64_t head_dim, float scale, float* out) {
  constexpr int rows = kRowsPerBlock<DimsPerLane>;
  const size_t bytes = shared_bytes(rows, head_dim);
  // Above 48 KB a kernel must opt in; done once per instantiation, for the largest head dimension it serves.
  static const bool opted_in = [] {
    cudaFuncSetAttribute(attention_kernel<DimsPerLane>, cudaFuncAttributeMaxDynamicSharedMemorySize,
                         int(shared_bytes(rows, 32 * DimsPerLane)));
    return true;
  }();
  (void)opted_in;
  const dim3 grid(unsigned((len_q + rows - 1) / rows), unsigned(heads), unsigned(batch));
  attention_kernel<DimsPerLane><<<grid, kWarps * 32, bytes, stream>>>(q, q_stride, k, v, kv_stride, mask, len_q,
                                                                     len_k, heads, kv_heads, int(head_dim), scale,
                                                                     out);
}

}  // namespace

bool attention(cudaStream_t stream, const float* q, int64_t q_stride, const float* k, const float* v,
               int64_t kv_stride, const uint8_t* mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads,
               int64_t kv_heads, int64_t head_dim, float scale, float* out) {
  if (head_dim > kMaxAttentionHeadDim) return false;
  if (batch <= 0 || len_q <= 0) return true;
  // Five and seven lanes' worth of dimensions run as six and eight: those two spilled registers on some targets.
  int64_t dims_per_lane = (head_dim + 31) / 32;
  if (dims_per_lane == 5 || dims_per_lane == 7) ++dims_per_lane;
  switch (dims_per_lane) {
#define TETHER_ATTENTION_CASE(n) \
  case n: launch<n>(stream, q, q_stride, k, v, kv_stride, mask, batch, len_q, len_k, heads, kv_heads, head_dim, scale, out); break;
    TETHER_ATTENTION_CASE(1)
    TETHER_ATTENTION_CASE(2)
    TETHER_ATTENTION_CASE(3)
    TETHER_ATTENTION_CASE(4)
    TETHER_ATTENTION_CASE(6)
    TETHER_ATTENTION_CASE(8)
#undef TETHER_ATTENTION_CASE
  }
  return true;
}

}  // namespace tether::cuda
