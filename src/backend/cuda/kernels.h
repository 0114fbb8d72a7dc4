// Launchers of the CUDA backend's own kernels (everything but the matrix products, which are cuBLASLt's). Each
// enqueues on `stream` and returns at once; pointers are device addresses. Host code includes this without nvcc.
#pragma once

#include <cuda_runtime_api.h>

#include <cstdint>
#include <string>

namespace tether::cuda {

// Whether this build holds code the current device can run; `why` names the device and the build's targets if not.
bool kernels_loadable(std::string* why);

enum class StoredType : int { f32 = 0, bf16 = 1, f16 = 2 };

void layer_norm(cudaStream_t stream, const float* x, int64_t rows, int64_t n, const float* gamma, const float* beta,
                float eps, float* y);
// kind: 0 weight * (x * inv), 1 (x * inv) * (1 + weight), 2 no weight. With scale/shift (mod_stride, rows_per_group)
// the normalised row is modulated as an adaptive norm's: y * (1 + scale) + shift.
void rms_norm(cudaStream_t stream, const float* x, int64_t rows, int64_t n, const float* weight, int kind, float eps,
              float* y, const float* scale = nullptr, const float* shift = nullptr, int64_t mod_stride = 0,
              int64_t rows_per_group = 1);
void modulate(cudaStream_t stream, float* y, int64_t rows, int64_t n, const float* scale, const float* shift,
              int64_t mod_stride, int64_t rows_per_group);
// cos and sin [tokens, head_dim / 2] of each position's rotary angles (angles: backend::RopeAngles as an int, see
// element_math.h rope_timescale), for rope_rotate.
void rope_angles(cudaStream_t stream, const int64_t* positions, int64_t tokens, int64_t head_dim, float max_wavelength,
                 int angles, float* cos, float* sin);
void rope_rotate(cudaStream_t stream, float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cos,
                 const float* sin);
// act: cuda_math::Act as an int.
void activate(cudaStream_t stream, float* x, int64_t n, int act);
void gated(cudaStream_t stream, const float* gate_up, int64_t rows, int64_t n, int act, float* out);
void add(cudaStream_t stream, const float* a, const float* b, int64_t n, float* out);
void scale(cudaStream_t stream, float* x, int64_t n, float s);
void gated_add(cudaStream_t stream, float* x, const float* y, const float* gate, int64_t gate_stride, int64_t rows,
               int64_t n, int64_t rows_per_group);
void copy_rows(cudaStream_t stream, const float* src, int64_t src_stride, float* dst, int64_t dst_stride, int64_t rows,
               int64_t width);
// out row i = table row ids[i] converted to float32, times scale; ids were checked against rows by the caller.
void gather_rows(cudaStream_t stream, const void* table, StoredType type, int64_t width, const int64_t* ids,
                 int64_t count, float scale, float* out, int64_t ldo);
// Patches of pixels [B, C, H, W] laid out as rows of [C, P, P]: cols [B * patches, C * P * P].
void im2col_patches(cudaStream_t stream, const float* pixels, int64_t batch, int64_t channels, int64_t height,
                    int64_t width, int64_t patch, float* cols);
void pixel_shuffle(cudaStream_t stream, const float* x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                   float* out);
void time_embedding(cudaStream_t stream, double time, int64_t dim, double min_period, double max_period, float* out);
void axpy(cudaStream_t stream, float* x, const float* v, int64_t n, float a);
void rtc_guide(cudaStream_t stream, const float* x, float* v, const float* target, const float* weights,
               int64_t chunk, int64_t width, float time, float guidance_weight);
// sums[0] = sum (v - prev)^2, sums[1] = sum prev^2 over the first action_dim of each row, in double.
void change_norms(cudaStream_t stream, const float* v, const float* prev, int64_t chunk, int64_t width,
                  int64_t action_dim, double* sums);
// float32 to bf16 (type bf16) or fp16 (type f16) storage, for the tensor-core products' inputs.
void convert_from_f32(cudaStream_t stream, const float* x, int64_t n, StoredType type, void* out);

// Masked grouped-query attention, the CPU backend's layout and masking rule (backend.h), as one fused kernel whose
// scores never leave the chip. Returns false when head_dim is above the kernel's limit (256).
bool attention(cudaStream_t stream, const float* q, int64_t q_stride, const float* k, const float* v,
               int64_t kv_stride, const uint8_t* mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads,
               int64_t kv_heads, int64_t head_dim, float scale, float* out);
constexpr int64_t kMaxAttentionHeadDim = 256;

}  // namespace tether::cuda
