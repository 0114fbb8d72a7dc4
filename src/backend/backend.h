// The compute interface every backend implements (the CPU today, CUDA next): a backend owns its buffers, knows
// where a tensor lives, and carries the operation table the model blocks call. Model code never does math itself.
#pragma once

#include <algorithm>
#include <cstdint>
#include <memory>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "backend/cpu/packed_linear.h"
#include "core/tensor.h"

namespace tether::backend {

enum class Device { cpu, cuda };
const char* device_name(Device d);

// An address in a backend's memory. Model code can offset it and hand it to the backend, but cannot read or write
// through it: on a GPU backend it is a device address. Only backends call address().
template <typename T>
class Ptr {
 public:
  Ptr() = default;
  explicit Ptr(T* p) : p_(p) {}
  template <typename U>
  Ptr(Ptr<U> other) requires std::is_convertible_v<U*, T*> : p_(other.address()) {}
  Ptr operator+(int64_t n) const { return Ptr(p_ + n); }
  explicit operator bool() const { return p_ != nullptr; }
  T* address() const { return p_; }

 private:
  T* p_ = nullptr;
};

// A typed array in one backend's memory (activations, caches, masks, constants). Moving keeps the storage.
template <typename T>
class Array {
 public:
  Array() = default;
  Array(std::shared_ptr<void> storage, T* base, int64_t size) : storage_(std::move(storage)), base_(base), size_(size) {}
  Ptr<T> at(int64_t offset = 0) const { return Ptr<T>(base_ + offset); }
  int64_t size() const { return size_; }
  bool empty() const { return size_ == 0; }

 private:
  std::shared_ptr<void> storage_;
  T* base_ = nullptr;
  int64_t size_ = 0;
};

// A linear layer's weights in the backend's own layout (packed once at load).
class LinearWeights {
 public:
  virtual ~LinearWeights() = default;
  virtual int64_t out_features() const = 0;
  virtual int64_t in_features() const = 0;
};

// A row-lookup table kept in its stored dtype (token embeddings): only the rows used are ever converted.
class Table {
 public:
  virtual ~Table() = default;
  virtual int64_t rows() const = 0;
  virtual int64_t width() const = 0;
};

// silu: x * sigmoid(x); gelu_tanh: GELU's tanh approximation; gelu_erf: the exact (erf) GELU; relu: max(x, 0).
enum class Activation { silu, gelu_tanh, gelu_erf, relu };
const char* activation_name(Activation a);

// RMSNorm flavours: Llama's x * rsqrt(mean(x^2) + eps) * w; Gemma's ... * (1 + w).
enum class RmsScale { weight, one_plus_weight };

// How RoPE angles are rounded in float32: lerobot's apply_rope (SmolVLA) divides the position by the timescale
// wavelength^(2i/D); transformers' rotary embedding (Gemma: pi0, pi0.5) multiplies it by inv_freq = 1 / base^(2i/D),
// a float32 buffer, which a model built in bfloat16 holds rounded to bf16 even after a later cast to float32.
enum class RopeAngles { timescale_division, inverse_frequency, inverse_frequency_bf16 };

// Multiply-add counts of the matrix products run so far (2 per multiply-add), for benchmarks' GFLOP/s.
struct FlopCounter {
  double linear = 0, attention = 0, other = 0;
  double total() const { return linear + attention + other; }
};

class Backend {
 public:
  virtual ~Backend() = default;
  virtual std::string name() const = 0;  // "cpu"
  virtual Device device() const = 0;

  // ---- memory
  template <typename T>
  Array<T> alloc(int64_t n) {
    auto storage = allocate_bytes(std::size_t(std::max<int64_t>(n, 1)) * sizeof(T));
    T* base = static_cast<T*>(storage.get());
    return Array<T>(std::move(storage), base, n);
  }
  // A constant from host memory (weights: norms, biases, position tables). A host backend keeps a view of `data`,
  // which the caller keeps alive as long as the backend uses it (the checkpoint mapping); a device backend copies it.
  virtual Array<float> constant(const float* data, int64_t n) = 0;
  virtual void upload(const void* host, std::size_t bytes, Ptr<void> dst) = 0;
  virtual void download(Ptr<const void> src, std::size_t bytes, void* host) = 0;
  template <typename T>
  void upload(const T* host, int64_t n, Ptr<T> dst) { upload(static_cast<const void*>(host), std::size_t(n) * sizeof(T), Ptr<void>(dst.address())); }
  template <typename T>
  void download(Ptr<const T> src, int64_t n, T* host) { download(Ptr<const void>(src.address()), std::size_t(n) * sizeof(T), host); }

  // ---- weights
  // weight: [n, k] row-major host float32 (nn.Linear), bias [n] or null; copied into the backend's layout.
  virtual std::unique_ptr<LinearWeights> pack_linear(const float* weight, int64_t n, int64_t k, const float* bias,
                                                     cpu::Precision precision) = 0;
  virtual std::unique_ptr<Table> table(const Tensor& host) = 0;

  // ---- operations (float32 unless said otherwise; all pointers are this backend's)
  // y[m, n] = x[m, k] W^T + b, or y += ... with accumulate; y has row stride ldy (0: n).
  virtual void linear(const LinearWeights& w, Ptr<const float> x, int64_t m, Ptr<float> y, bool accumulate = false,
                      int64_t ldy = 0) = 0;
  virtual void layer_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> gamma, Ptr<const float> beta,
                          float eps, Ptr<float> y) = 0;
  virtual void rms_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> weight, float eps, Ptr<float> y,
                        RmsScale kind = RmsScale::weight) = 0;
  // Adaptive RMSNorm: y = rms_norm(x) * (1 + scale) + shift, without a weight; scale and shift are rows of n with row
  // stride mod_stride (a [scale | shift | gate] modulation), and row r of x uses group r / rows_per_group (one
  // conditioning vector per batch item).
  virtual void rms_norm_modulated(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> scale,
                                  Ptr<const float> shift, int64_t mod_stride, int64_t rows_per_group, float eps,
                                  Ptr<float> y) = 0;
  // In place over rows of n: y = y * (1 + scale) + shift, the scale and shift rows (stride mod_stride) of group
  // r / rows_per_group (an adaptive LayerNorm's modulation after a LayerNorm without affine).
  virtual void modulate(Ptr<float> y, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                        int64_t mod_stride, int64_t rows_per_group) = 0;
  // Masked grouped-query attention (see cpu/kernels.h `attention` for the layout and the masking rule).
  virtual void attention(Ptr<const float> q, int64_t q_stride, Ptr<const float> k, Ptr<const float> v,
                         int64_t kv_stride, Ptr<const uint8_t> mask, int64_t batch, int64_t len_q, int64_t len_k,
                         int64_t heads, int64_t kv_heads, int64_t head_dim, float scale, Ptr<float> out) = 0;
  // Rotary embedding in place on x[batch, len, heads, head_dim] (split-halves layout), positions [batch, len].
  virtual void rope(Ptr<float> x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim,
                    Ptr<const int64_t> positions, float max_wavelength,
                    RopeAngles angles = RopeAngles::timescale_division) = 0;
  // Rotary embedding in place from precomputed angles: x[rows, heads, head_dim] (split halves), cos and sin
  // [rows, head_dim / 2]; x1' = x1 cos - x2 sin, x2' = x2 cos + x1 sin. For position schemes the model computes
  // itself (Qwen3-VL's interleaved multimodal RoPE and its vision tower's 2-D rotary).
  virtual void rope_rotate(Ptr<float> x, int64_t rows, int64_t heads, int64_t head_dim, Ptr<const float> cos,
                           Ptr<const float> sin) = 0;
  virtual void activate(Ptr<float> x, int64_t n, Activation act) = 0;
  // Gated linear unit over rows of [gate | up] (width 2 * n): out[r] = act(gate) * up; out is [rows, n].
  virtual void gated(Ptr<const float> gate_up, int64_t rows, int64_t n, Activation act, Ptr<float> out) = 0;
  virtual void add(Ptr<const float> a, Ptr<const float> b, int64_t n, Ptr<float> out) = 0;  // out may alias
  virtual void scale(Ptr<float> x, int64_t n, float s) = 0;
  // x[r] += y[r] * gate[r / rows_per_group] elementwise over rows of n, gate rows with stride gate_stride (adaptive
  // norms' gated residual).
  virtual void gated_add(Ptr<float> x, Ptr<const float> y, Ptr<const float> gate, int64_t gate_stride, int64_t rows,
                         int64_t n, int64_t rows_per_group) = 0;
  // dst row r = src row r (row strides in elements; src_stride 0 broadcasts one row).
  virtual void copy_rows(Ptr<const float> src, int64_t src_stride, Ptr<float> dst, int64_t dst_stride, int64_t rows,
                         int64_t width) = 0;
  // out row i = table row ids[i] (converted to float32) * scale; out has row stride ldo (0: width).
  virtual void gather_rows(const Table& table, Ptr<const int64_t> ids, int64_t count, float scale, Ptr<float> out,
                           int64_t ldo = 0) = 0;
  // Conv2d with kernel = stride = patch, pixels [B, C, H, W] -> [B, patches, embed].
  virtual void patch_embed(Ptr<const float> pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                           Ptr<const float> weight, Ptr<const float> bias, int64_t embed, int64_t patch,
                           Ptr<float> out) = 0;
  virtual void pixel_shuffle(Ptr<const float> x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                             Ptr<float> out) = 0;
  // Sinusoidal embedding of one time value [dim]: sin half then cos half, periods min * (max/min)^fraction with
  // torch.linspace's fractions, computed in float64 and rounded (lerobot's create_sinusoidal_pos_embedding).
  virtual void time_embedding(double time, int64_t dim, double min_period, double max_period, Ptr<float> out) = 0;

  // ---- the sampler's step
  virtual void axpy(Ptr<float> x, Ptr<const float> v, int64_t n, float a) = 0;  // x += a * v
  // RTC guidance on one item's velocity [chunk, width], in place (models/blocks/sampler.h says what it computes).
  virtual void rtc_guide(Ptr<const float> x, Ptr<float> v, Ptr<const float> target, Ptr<const float> weights,
                         int64_t chunk, int64_t width, float time, float guidance_weight) = 0;
  // sum (v - prev)^2 and sum prev^2 over the first action_dim of every row of [chunk, width], in float64.
  virtual std::pair<double, double> change_norms(Ptr<const float> v, Ptr<const float> prev, int64_t chunk,
                                                 int64_t width, int64_t action_dim) = 0;

  // Waits for queued work (a no-op on the CPU, where every op completes before it returns).
  virtual void synchronize() {}

  // Matrix-product flops run through this backend since it was made.
  const FlopCounter& flops() const { return flops_; }

 protected:
  virtual std::shared_ptr<void> allocate_bytes(std::size_t bytes) = 0;
  FlopCounter flops_;
};

// The backends compiled into this binary, by name ("cpu", and "cuda" when nvcc built it), and one of them made on
// request. make_backend("cuda") on a machine with no usable device throws Error(unavailable) whose message is one line
// saying why; "auto" makes the first usable of cuda, cpu.
std::vector<std::string> compiled_backends();
std::shared_ptr<Backend> make_backend(const std::string& name = "cpu");

// The backend a model gets when its load options name none: TETHER_BACKEND (cpu, cuda or auto) when set, else the
// CPU. It lets a whole test suite run on another backend unchanged (scripts/check_cuda.sh runs the parity suite so).
std::shared_ptr<Backend> make_default_backend();

// Whether make_backend(name) would succeed here; when not, `why` (if given) gets the one-line reason. Cheap enough to
// call per command (it opens no model), and never throws.
bool backend_usable(const std::string& name, std::string* why = nullptr);
// "auto" resolved to the backend it picks on this machine ("cuda" when compiled and a device is usable, else "cpu");
// any other name is returned as it is (unknown names fail later, in make_backend).
std::string resolve_backend(const std::string& name);

}  // namespace tether::backend
