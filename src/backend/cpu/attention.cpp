// Masked grouped-query attention: per (batch, head, block of queries) one product for the scores, a scale/mask/softmax
// pass, and one product with V, in the order lerobot's eager attention uses. Both products are the panel kernel's
// fixed-order chains: a masked key adds exact zeros, so an item's result does not depend on how far its batch-mates
// pad the sequence, nor on the CPU's vector width. Each K and V head is packed into panels once, then read by every
// block of queries and every head of its group (pi0's Gemma has 8 heads on one K/V head).

#include <algorithm>
#include <limits>
#include <string>
#include <vector>

#include "backend/cpu/panel_gemm.h"
#include "backend/cpu/kernels.h"
#include "core/error.h"

namespace tether::cpu {
namespace {

// Rows of queries per task: a block's scores (128 x 1024 for SigLIP at 512 px) stay in L2.
constexpr int64_t kQueryBlock = 128;

// The message is built only on failure: this runs inside the denoise loop, which must not allocate.
template <typename Message>
void require(bool ok, Message&& what) {
  if (!ok) throw Error(ErrorCode::invalid_argument, "attention: " + std::string(what()));
}

}  // namespace

void attention(const float* q, int64_t q_stride, const float* k, const float* v, int64_t kv_stride,
               const uint8_t* mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
               int64_t head_dim, float scale, float* out) {
  require(heads > 0 && kv_heads > 0 && heads % kv_heads == 0,
          [&] { return std::to_string(heads) + " heads cannot share " + std::to_string(kv_heads) + " kv heads"; });
  require(head_dim > 0, [] { return "head_dim must be positive"; });
  require(q_stride >= heads * head_dim, [&] { return "q_stride " + std::to_string(q_stride) + " < heads * head_dim"; });
  require(kv_stride >= kv_heads * head_dim,
          [&] { return "kv_stride " + std::to_string(kv_stride) + " < kv_heads * head_dim"; });
  require(len_k > 0 || len_q == 0, [] { return "no keys to attend to"; });
  require(len_k <= std::numeric_limits<int>::max() && q_stride <= std::numeric_limits<int>::max() &&
              kv_stride <= std::numeric_limits<int>::max(),
          [] { return "sizes exceed the integer range"; });
  if (batch <= 0 || len_q <= 0) return;

  const int64_t groups = heads / kv_heads;
  const int64_t out_stride = heads * head_dim;
  // Tasks are (item, head, block of queries); each row's chains are the same in any block, so the layout only
  // trades the scores' cache footprint against parallelism.
  const int64_t block = std::min<int64_t>(len_q, kQueryBlock);
  const int64_t blocks = (len_q + block - 1) / block;
  const int64_t tasks = batch * heads * blocks;
  const bool parallel = tasks > 1 && batch * heads * len_q * len_k * head_dim >= (1 << 16);
  constexpr float kMasked = std::numeric_limits<float>::lowest();

  // K^T (len_k columns over head_dim) and V (head_dim columns over len_k) of every (item, K/V head), packed once.
  const int64_t k_floats = detail::packed_b_floats(len_k, head_dim);
  const int64_t v_floats = detail::packed_b_floats(head_dim, len_k);
  const int64_t kv_count = batch * kv_heads;
  thread_local std::vector<float> packed;  // the calling thread's; grows once, then reused
  if (packed.size() < std::size_t(kv_count * (k_floats + v_floats)))
    packed.resize(std::size_t(kv_count * (k_floats + v_floats)));
  float* const packed_kv = packed.data();

#pragma omp parallel if (parallel)
  {
#pragma omp for schedule(static)
    for (int64_t g = 0; g < kv_count; ++g) {
      const int64_t b = g / kv_heads, kh = g % kv_heads;
      float* kp = packed_kv + g * (k_floats + v_floats);
      detail::pack_b_panels(len_k, head_dim, k + b * len_k * kv_stride + kh * head_dim, kv_stride, /*trans_b=*/true,
                            kp);
      detail::pack_b_panels(head_dim, len_k, v + b * len_k * kv_stride + kh * head_dim, kv_stride, /*trans_b=*/false,
                            kp + k_floats);
    }
#pragma omp for schedule(dynamic)
    for (int64_t task = 0; task < tasks; ++task) {
      const int64_t b = task / (heads * blocks);
      const int64_t h = (task / blocks) % heads;
      const int64_t q0 = (task % blocks) * block;
      const int rows = int(std::min(block, len_q - q0));
      // Scores for one block, reused across calls; a product inside the parallel region runs single-threaded.
      thread_local std::vector<float> scores;
      if (scores.size() < std::size_t(block * len_k)) scores.resize(std::size_t(block * len_k));
      float* s = scores.data();
      const float* qp = q + (b * len_q + q0) * q_stride + h * head_dim;
      const float* kp = packed_kv + (b * kv_heads + h / groups) * (k_floats + v_floats);
      detail::gemm_packed_b(rows, len_k, head_dim, qp, q_stride, kp, s, len_k);
      for (int r = 0; r < rows; ++r) {
        float* sr = s + r * len_k;
        // The scale multiplies the finished dot products (not q), as upstream does.
        const uint8_t* mr = mask ? mask + (b * len_q + q0 + r) * len_k : nullptr;
        if (mr) {
#pragma omp simd
          for (int64_t j = 0; j < len_k; ++j) sr[j] = mr[j] ? sr[j] * scale : kMasked;
        } else {
#pragma omp simd
          for (int64_t j = 0; j < len_k; ++j) sr[j] = sr[j] * scale;
        }
        softmax_row(sr, len_k, mr);
      }
      float* o = out + (b * len_q + q0) * out_stride + h * head_dim;
      detail::gemm_packed_b(rows, head_dim, len_k, s, len_k, kp + k_floats, o, out_stride);
    }
  }
}

}  // namespace tether::cpu
