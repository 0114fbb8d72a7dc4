// Hand-written vector kernels the models need, float32, row-major. Each has a plain reference test.
#pragma once

#include <cstdint>

namespace tether::cpu {

// LayerNorm over the last dimension (rows x n): (x - mean) / sqrt(var + eps) * gamma + beta.
void layer_norm(const float* x, int64_t rows, int64_t n, const float* gamma, const float* beta, float eps, float* y);

// Llama RMSNorm: x * rsqrt(mean(x^2) + eps) * weight, computed in float32; one_plus: Gemma's (x * rsqrt) * (1 + weight).
// A null weight normalises alone.
void rms_norm(const float* x, int64_t rows, int64_t n, const float* weight, float eps, float* y, bool one_plus = false);

// Rotary embedding in place on x[B, L, H, D] (contiguous), "split halves" layout as in lerobot's apply_rope:
// first half i pairs with second half i, frequency max_wavelength^(-2i/D), angle = position / timescale; with
// inverse_frequency, transformers' rounding: inv_freq = 1 / base^(float(2i) / D) in float32 (rounded to bf16 with
// inverse_frequency_bf16), angle = position * inv_freq. positions is [B, L].
enum class RopeAngles { timescale_division, inverse_frequency, inverse_frequency_bf16 };
void rope(float* x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim, const int64_t* positions,
          float max_wavelength, RopeAngles angles = RopeAngles::timescale_division);

// Rotary embedding in place from precomputed angles: x [rows, heads, head_dim] (split halves), cos and sin
// [rows, head_dim / 2], the same angles for every head of a row.
void rope_rotate(float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cos, const float* sin);

// Masked grouped-query attention.
// q: [B, Lq, H, D] with row stride q_stride between tokens (elements); k, v: [B, Lk, KvH, D] with token stride
// kv_stride; mask: [B, Lq, Lk] bytes, nonzero = may attend (null = attend everywhere). out: [B, Lq, H*D].
// Scores are scaled by `scale`; masked scores become the lowest float (not -inf) so a fully masked row
// softmaxes to uniform, exactly as the reference does.
void attention(const float* q, int64_t q_stride, const float* k, const float* v, int64_t kv_stride,
               const uint8_t* mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
               int64_t head_dim, float scale, float* out);

// Softmax over each row of length n, in place: exp(x - max) / sum, with the sum's reciprocal applied as
// a multiply. A row of equal values (e.g. all masked) becomes uniform.
void softmax_rows(float* x, int64_t rows, int64_t n);
// One row, single-threaded (for callers already inside a parallel region). With `keep` (nonzero = a real key), the
// sum runs over the kept entries alone, in order (masked ones are exact zeros), so masked padding anywhere in the
// row, as batching adds it, cannot change the result; a row with nothing kept is uniform.
void softmax_row(float* x, int64_t n, const uint8_t* keep = nullptr);

// Sum of x[0, n) over 8 fixed lanes (element i in lane i % 8) joined by a fixed tree: vectorised, the same on every
// ISA, and unchanged by trailing zeros.
float lane_sum(const float* x, int64_t n);

// Activations, in place. gelu_tanh is PyTorch's GELU(approximate="tanh") (transformers'
// "gelu_pytorch_tanh"); silu is x * sigmoid(x). Both are within a few ulp of the exact functions.
void gelu_tanh(float* x, int64_t n);
void silu(float* x, int64_t n);
// PyTorch's exact GELU, (x * 0.5) * (1 + erf(x / sqrt(2))); relu: max(x, 0) (NaN stays NaN).
void gelu_erf(float* x, int64_t n);
void relu(float* x, int64_t n);
// out[i] = silu(gate[i]) * up[i]; out may alias gate.
void silu_mul(const float* gate, const float* up, int64_t n, float* out);
// out = gelu_tanh(gate) * up, with gelu's result rounded to float32 before the product (as upstream's separate tensors).
void gelu_tanh_mul(const float* gate, const float* up, int64_t n, float* out);

void add(const float* a, const float* b, int64_t n, float* out);  // out may alias a or b
void scale(float* x, int64_t n, float s);

// Conv2d with kernel = stride = patch (no padding), as a patch embedding.
// pixels: [B, C, H, W]; weight: [E, C, P, P]; bias: [E]; out: [B, (H/P)*(W/P), E] (row-major patches).
void patch_embed(const float* pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                 const float* weight, const float* bias, int64_t embed, int64_t patch, float* out);

// Idefics3/SmolVLM pixel shuffle: x [B, S, E] with S a square number of patches (side = sqrt(S)) to
// out [B, S / r^2, E * r^2], the exact element order of the upstream view/permute/reshape sequence.
void pixel_shuffle(const float* x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio, float* out);

}  // namespace tether::cpu
