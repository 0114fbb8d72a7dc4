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

// Packed K and V held at once, in floats (8 MB): 16 SigLIP heads at 1024 tokens, whatever the batch.
constexpr int64_t kMaxPackedFloats = int64_t(2) << 20;

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
  const bool parallel = batch * heads * blocks > 1 && batch * heads * len_q * len_k * head_dim >= (1 << 16);
  constexpr float kMasked = std::numeric_limits<float>::lowest();

  // K^T (len_k columns over head_dim) and V (head_dim columns over len_k) of each (item, K/V head), packed once.
  // The (item, K/V head) pairs go in runs whose panels fit kMaxPackedFloats, so a large batch does not hold all of
  // them at once.
  const int64_t k_floats = detail::packed_b_floats(len_k, head_dim);
  const int64_t pair_floats = k_floats + detail::packed_b_floats(head_dim, len_k);
  const int64_t pairs = batch * kv_heads;
  const int64_t run = std::clamp<int64_t>(kMaxPackedFloats / pair_floats, 1, pairs);
  thread_local std::vector<float> packed;  // the calling thread's; grows once, then reused
  if (packed.size() < std::size_t(run * pair_floats)) packed.resize(std::size_t(run * pair_floats));
  float* const packed_kv = packed.data();

  for (int64_t g0 = 0; g0 < pairs; g0 += run) {
    const int64_t g1 = std::min(pairs, g0 + run);
    const int64_t tasks = (g1 - g0) * groups * blocks;
#pragma omp parallel if (parallel)
    {
      // K and V are packed as separate items, so that one K/V head (pi0's) keeps two threads busy.
#pragma omp for schedule(static)
      for (int64_t item = 2 * g0; item < 2 * g1; ++item) {
        const int64_t g = item / 2, b = g / kv_heads, kh = g % kv_heads;
        float* kp = packed_kv + (g - g0) * pair_floats;
        const int64_t offset = b * len_k * kv_stride + kh * head_dim;
        if (item % 2 == 0) detail::pack_b_panels(len_k, head_dim, k + offset, kv_stride, /*trans_b=*/true, kp);
        else detail::pack_b_panels(head_dim, len_k, v + offset, kv_stride, /*trans_b=*/false, kp + k_floats);
      }
#pragma omp for schedule(dynamic)
      for (int64_t task = 0; task < tasks; ++task) {
        const int64_t g = g0 + task / (groups * blocks);
        const int64_t b = g / kv_heads;
        const int64_t h = (g % kv_heads) * groups + (task / blocks) % groups;
        const int64_t q0 = (task % blocks) * block;
        const int rows = int(std::min(block, len_q - q0));
        // Scores for one block, reused across calls; a product inside the parallel region runs single-threaded.
        thread_local std::vector<float> scores;
        if (scores.size() < std::size_t(block * len_k)) scores.resize(std::size_t(block * len_k));
        float* s = scores.data();
        const float* qp = q + (b * len_q + q0) * q_stride + h * head_dim;
        const float* kp = packed_kv + (g - g0) * pair_floats;
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
}

}  // namespace tether::cpu
