// The CUDA backend: the Backend interface over one device and one stream. Weights are uploaded once at load; every
// operation is enqueued on the stream and returns at once; download waits for the stream. Host code (no kernels):
// compiled by the C++ compiler against the CUDA runtime and cuBLASLt headers.
#include "backend/cuda/cuda_backend.h"

#include <cublasLt.h>
#include <cuda_runtime_api.h>
#include <dlfcn.h>

#include <cmath>
#include <cstring>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include "backend/cuda/device_pool.h"
#include "backend/cuda/element_math.h"
#include "backend/cuda/kernels.h"
#include "core/dtype.h"
#include "core/error.h"

namespace tether::backend {
namespace {

using cuda::StoredType;

void check(cudaError_t status, const char* what) {
  if (status != cudaSuccess)
    throw Error(ErrorCode::internal, std::string("cuda: ") + what + ": " + cudaGetErrorString(status));
}

void check(cublasStatus_t status, const char* what) {
  if (status != CUBLAS_STATUS_SUCCESS)
    throw Error(ErrorCode::internal, std::string("cuda: ") + what + ": cuBLASLt status " + std::to_string(int(status)));
}

std::string mib(std::size_t bytes) { return std::to_string((bytes + (1 << 20) - 1) >> 20) + " MiB"; }

std::size_t stored_size(StoredType t) { return t == StoredType::f32 ? 4 : 2; }

cudaDataType_t cuda_type(StoredType t) {
  return t == StoredType::f32 ? CUDA_R_32F : t == StoredType::bf16 ? CUDA_R_16BF : CUDA_R_16F;
}

StoredType stored_type(cpu::Precision p) {
  return p == cpu::Precision::bf16 ? StoredType::bf16 : p == cpu::Precision::fp16 ? StoredType::f16 : StoredType::f32;
}

// The largest power of two up to 16 dividing both the address and the row pitch: what cuBLASLt may assume.
int alignment(const void* p, int64_t row_bytes) {
  const auto bits = reinterpret_cast<uintptr_t>(p) | uintptr_t(row_bytes);
  int a = 16;
  while (a > 1 && (bits % uintptr_t(a)) != 0) a /= 2;
  return a;
}

class CudaLinear final : public LinearWeights {
 public:
  int64_t n = 0, k = 0;
  StoredType type = StoredType::f32;
  std::shared_ptr<void> weight, bias;  // weight [n, k] row-major in `type`; bias [n] float32 or null
  int64_t out_features() const override { return n; }
  int64_t in_features() const override { return k; }
};

class CudaTable final : public Table {
 public:
  int64_t row_count = 0, row_width = 0;
  StoredType type = StoredType::f32;
  std::shared_ptr<void> data;
  int64_t rows() const override { return row_count; }
  int64_t width() const override { return row_width; }
};

// One matrix product's cuBLASLt set-up, made once per shape and reused: y[m, n] (row pitch ldy) = x[m, k] W^T (+ b)
// (+ y). In cuBLASLt's column-major terms, D [n x m] = op(A) B with A = W viewed as [k x n] and transposed.
struct GemmKey {
  int64_t m, n, k, ldy;
  StoredType type;
  bool accumulate, bias;
  int align;
  auto tie() const { return std::tie(m, n, k, ldy, type, accumulate, bias, align); }
  bool operator<(const GemmKey& o) const { return tie() < o.tie(); }
};

struct GemmPlan {
  cublasLtMatmulDesc_t desc = nullptr;
  cublasLtMatrixLayout_t a = nullptr, b = nullptr, c = nullptr;
  cublasLtMatmulAlgo_t algo{};
  ~GemmPlan() {
    if (desc) cublasLtMatmulDescDestroy(desc);
    for (auto layout : {a, b, c})
      if (layout) cublasLtMatrixLayoutDestroy(layout);
  }
};

class CudaBackend final : public Backend {
 public:
  CudaBackend()
      : pool_([](std::size_t bytes) -> void* {
                void* p = nullptr;
                if (cudaMalloc(&p, bytes) != cudaSuccess) {
                  cudaGetLastError();  // clear the sticky-free out-of-memory error
                  return nullptr;
                }
                return p;
              },
              [](void* p) { cudaFree(p); }) {
    check(cudaSetDevice(0), "cudaSetDevice");
    check(cudaGetDeviceProperties(&props_, 0), "cudaGetDeviceProperties");
    check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreate");
    check(cublasLtCreate(&lt_), "cublasLtCreate");
    workspace_ = allocate_bytes(kWorkspaceBytes);
    sums_ = alloc<double>(2);
  }
  ~CudaBackend() override {
    cudaStreamSynchronize(stream_);
    plans_.clear();
    cublasLtDestroy(lt_);
    cudaStreamDestroy(stream_);
  }

  std::string name() const override { return "cuda"; }
  Device device() const override { return Device::cuda; }

  Array<float> constant(const float* data, int64_t n) override {
    Array<float> a = alloc<float>(n);
    if (n > 0) check(cudaMemcpyAsync(a.at().address(), data, std::size_t(n) * 4, cudaMemcpyHostToDevice, stream_), "upload");
    return a;
  }
  void upload(const void* host, std::size_t bytes, Ptr<void> dst) override {
    // From pageable memory the call returns once the bytes are staged, so the caller may reuse its buffer at once.
    if (bytes) check(cudaMemcpyAsync(dst.address(), host, bytes, cudaMemcpyHostToDevice, stream_), "upload");
  }
  void download(Ptr<const void> src, std::size_t bytes, void* host) override {
    if (bytes) check(cudaMemcpyAsync(host, src.address(), bytes, cudaMemcpyDeviceToHost, stream_), "download");
    synchronize();
  }
  void synchronize() override { check(cudaStreamSynchronize(stream_), "a kernel or copy on the stream"); }

  std::unique_ptr<LinearWeights> pack_linear(const float* weight, int64_t n, int64_t k, const float* bias,
                                             cpu::Precision precision) override {
    auto w = std::make_unique<CudaLinear>();
    w->n = n, w->k = k, w->type = stored_type(precision);
    const std::size_t count = std::size_t(n) * std::size_t(k);
    w->weight = allocate_bytes(count * stored_size(w->type));
    if (w->type == StoredType::f32) {
      copy_in(weight, count * 4, w->weight.get());
    } else {
      std::vector<uint16_t> half(count);
      for (std::size_t i = 0; i < count; ++i)
        half[i] = w->type == StoredType::bf16 ? f32_to_bf16(weight[i]) : f32_to_f16(weight[i]);
      copy_in(half.data(), count * 2, w->weight.get());
    }
    if (bias) {
      w->bias = allocate_bytes(std::size_t(n) * 4);
      copy_in(bias, std::size_t(n) * 4, w->bias.get());
    }
    return w;
  }
  std::unique_ptr<Table> table(const Tensor& host) override {
    if (host.shape.size() != 2)
      throw Error(ErrorCode::invalid_argument, "table: expected a 2-d tensor, got " + shape_str(host.shape));
    auto t = std::make_unique<CudaTable>();
    t->row_count = host.dim(0), t->row_width = host.dim(1);
    if (host.dtype == DType::bf16 || host.dtype == DType::f16 || host.dtype == DType::f32) {
      // Kept in the stored dtype: a 150k-row vocabulary stays half size on the device.
      t->type = host.dtype == DType::bf16 ? StoredType::bf16 : host.dtype == DType::f16 ? StoredType::f16 : StoredType::f32;
      t->data = allocate_bytes(host.nbytes());
      copy_in(host.data, host.nbytes(), t->data.get());
    } else {
      std::vector<float> f(std::size_t(host.numel()));
      host.copy_f32(0, host.numel(), f.data());
      t->data = allocate_bytes(f.size() * 4);
      copy_in(f.data(), f.size() * 4, t->data.get());
    }
    return t;
  }

  void linear(const LinearWeights& weights, Ptr<const float> x, int64_t m, Ptr<float> y, bool accumulate,
              int64_t ldy) override {
    const auto& w = static_cast<const CudaLinear&>(weights);
    flops_.linear += 2.0 * double(m) * double(w.n) * double(w.k);
    if (m <= 0) return;
    const void* input = x.address();
    if (w.type != StoredType::f32) {
      // Tensor cores take both operands in the weights' half type: the activations are rounded once here.
      const std::size_t bytes = std::size_t(m * w.k) * 2;
      ensure(half_input_, bytes);
      cuda::convert_from_f32(stream_, x.address(), m * w.k, w.type, half_input_.get());
      input = half_input_.get();
    }
    gemm(w.weight.get(), input, w.type, m, w.n, w.k, y.address(), ldy == 0 ? w.n : ldy,
         static_cast<const float*>(w.bias.get()), accumulate);
  }
  void layer_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> gamma, Ptr<const float> beta,
                  float eps, Ptr<float> y) override {
    require(n > 0, "layer_norm: row length must be positive");
    cuda::layer_norm(stream_, x.address(), rows, n, gamma.address(), beta.address(), eps, y.address());
    launched("layer_norm");
  }
  void rms_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> weight, float eps, Ptr<float> y,
                RmsScale kind) override {
    require(n > 0, "rms_norm: row length must be positive");
    const int k = !weight ? 2 : kind == RmsScale::one_plus_weight ? 1 : 0;
    cuda::rms_norm(stream_, x.address(), rows, n, weight.address(), k, eps, y.address());
    launched("rms_norm");
  }
  void rms_norm_modulated(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                          int64_t mod_stride, int64_t rows_per_group, float eps, Ptr<float> y) override {
    require(rows_per_group >= 1, "rms_norm_modulated: rows_per_group must be >= 1");
    require(n > 0, "rms_norm_modulated: row length must be positive");
    cuda::rms_norm(stream_, x.address(), rows, n, nullptr, 2, eps, y.address(), scale.address(), shift.address(),
                   mod_stride, rows_per_group);
    launched("rms_norm_modulated");
  }
  void modulate(Ptr<float> y, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                int64_t mod_stride, int64_t rows_per_group) override {
    require(rows_per_group >= 1, "modulate: rows_per_group must be >= 1");
    cuda::modulate(stream_, y.address(), rows, n, scale.address(), shift.address(), mod_stride, rows_per_group);
    launched("modulate");
  }
  void attention(Ptr<const float> q, int64_t q_stride, Ptr<const float> k, Ptr<const float> v, int64_t kv_stride,
                 Ptr<const uint8_t> mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
                 int64_t head_dim, float scale, Ptr<float> out) override {
    require(heads > 0 && kv_heads > 0 && heads % kv_heads == 0, "attention: heads must be a multiple of kv_heads");
    require(head_dim > 0, "attention: head_dim must be positive");
    require(q_stride >= heads * head_dim, "attention: q_stride < heads * head_dim");
    require(kv_stride >= kv_heads * head_dim, "attention: kv_stride < kv_heads * head_dim");
    require(len_k > 0 || len_q == 0, "attention: no keys to attend to");
    if (head_dim > cuda::kMaxAttentionHeadDim)
      throw Error(ErrorCode::unsupported, "attention: head_dim " + std::to_string(head_dim) +
                                              " is above the CUDA kernel's " +
                                              std::to_string(cuda::kMaxAttentionHeadDim));
    flops_.attention += 4.0 * double(batch) * double(heads) * double(len_q) * double(len_k) * double(head_dim);
    cuda::attention(stream_, q.address(), q_stride, k.address(), v.address(), kv_stride, mask.address(), batch, len_q,
                    len_k, heads, kv_heads, head_dim, scale, out.address());
    launched("attention");
  }
  void rope(Ptr<float> x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim, Ptr<const int64_t> positions,
            float max_wavelength, RopeAngles angles) override {
    require(head_dim > 0 && head_dim % 2 == 0, "rope: head_dim must be even");
    const int64_t tokens = batch * len, half = head_dim / 2;
    ensure(rope_table_, std::size_t(2 * tokens * half) * 4);
    float* cos = static_cast<float*>(rope_table_.get());
    cuda::rope_angles(stream_, positions.address(), tokens, head_dim, max_wavelength, int(angles), cos,
                      cos + tokens * half);
    cuda::rope_rotate(stream_, x.address(), tokens, heads, head_dim, cos, cos + tokens * half);
    launched("rope");
  }
  void rope_rotate(Ptr<float> x, int64_t rows, int64_t heads, int64_t head_dim, Ptr<const float> cos,
                   Ptr<const float> sin) override {
    require(head_dim > 0 && head_dim % 2 == 0, "rope_rotate: head_dim must be even");
    cuda::rope_rotate(stream_, x.address(), rows, heads, head_dim, cos.address(), sin.address());
    launched("rope_rotate");
  }
  void activate(Ptr<float> x, int64_t n, Activation act) override {
    cuda::activate(stream_, x.address(), n, int(to_math(act)));
    launched("activate");
  }
  void gated(Ptr<const float> gate_up, int64_t rows, int64_t n, Activation act, Ptr<float> out) override {
    if (act != Activation::silu && act != Activation::gelu_tanh)
      throw Error(ErrorCode::unsupported, std::string("gated: no gated form of ") + activation_name(act));
    cuda::gated(stream_, gate_up.address(), rows, n, int(to_math(act)), out.address());
    launched("gated");
  }
  void add(Ptr<const float> a, Ptr<const float> b, int64_t n, Ptr<float> out) override {
    cuda::add(stream_, a.address(), b.address(), n, out.address());
    launched("add");
  }
  void scale(Ptr<float> x, int64_t n, float s) override {
    cuda::scale(stream_, x.address(), n, s);
    launched("scale");
  }
  void gated_add(Ptr<float> x, Ptr<const float> y, Ptr<const float> gate, int64_t gate_stride, int64_t rows, int64_t n,
                 int64_t rows_per_group) override {
    require(rows_per_group >= 1, "gated_add: rows_per_group must be >= 1");
    cuda::gated_add(stream_, x.address(), y.address(), gate.address(), gate_stride, rows, n, rows_per_group);
    launched("gated_add");
  }
  void copy_rows(Ptr<const float> src, int64_t src_stride, Ptr<float> dst, int64_t dst_stride, int64_t rows,
                 int64_t width) override {
    cuda::copy_rows(stream_, src.address(), src_stride, dst.address(), dst_stride, rows, width);
    launched("copy_rows");
  }
  void gather_rows(const Table& table, Ptr<const int64_t> ids, int64_t count, float scale, Ptr<float> out,
                   int64_t ldo) override {
    const auto& t = static_cast<const CudaTable&>(table);
    // The ids are checked on the host first (one small copy; the prefix runs this once per request): a bad id is a
    // clear error, never a read outside the table.
    ids_host_.resize(std::size_t(count));
    download(Ptr<const void>(ids.address()), std::size_t(count) * sizeof(int64_t), ids_host_.data());
    for (int64_t id : ids_host_)
      if (id < 0 || id >= t.row_count)
        throw Error(ErrorCode::internal, "gather_rows: id " + std::to_string(id) + " outside the table's " +
                                             std::to_string(t.row_count) + " rows");
    cuda::gather_rows(stream_, t.data.get(), t.type, t.row_width, ids.address(), count, scale, out.address(),
                      ldo == 0 ? t.row_width : ldo);
    launched("gather_rows");
  }
  void patch_embed(Ptr<const float> pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                   Ptr<const float> weight, Ptr<const float> bias, int64_t embed, int64_t patch,
                   Ptr<float> out) override {
    require(patch > 0 && height % patch == 0 && width % patch == 0,
            "patch_embed: the image is not a multiple of the patch");
    const int64_t patches = batch * (height / patch) * (width / patch), col_len = channels * patch * patch;
    flops_.linear += 2.0 * double(patches) * double(embed) * double(col_len);
    ensure(patch_cols_, std::size_t(patches * col_len) * 4);
    float* cols = static_cast<float*>(patch_cols_.get());
    cuda::im2col_patches(stream_, pixels.address(), batch, channels, height, width, patch, cols);
    launched("patch_embed");
    gemm(weight.address(), cols, StoredType::f32, patches, embed, col_len, out.address(), embed, bias.address(), false);
  }
  void pixel_shuffle(Ptr<const float> x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                     Ptr<float> out) override {
    const auto side = int64_t(std::llround(std::sqrt(double(seq))));
    require(side * side == seq, "pixel_shuffle: the sequence length is not a square");
    require(ratio > 0 && side % ratio == 0, "pixel_shuffle: the side is not divisible by the ratio");
    cuda::pixel_shuffle(stream_, x.address(), batch, seq, embed, ratio, out.address());
    launched("pixel_shuffle");
  }
  void time_embedding(double time, int64_t dim, double min_period, double max_period, Ptr<float> out) override {
    cuda::time_embedding(stream_, time, dim, min_period, max_period, out.address());
    launched("time_embedding");
  }

  void axpy(Ptr<float> x, Ptr<const float> v, int64_t n, float a) override {
    cuda::axpy(stream_, x.address(), v.address(), n, a);
    launched("axpy");
  }
  void rtc_guide(Ptr<const float> x, Ptr<float> v, Ptr<const float> target, Ptr<const float> weights, int64_t chunk,
                 int64_t width, float time, float guidance_weight) override {
    cuda::rtc_guide(stream_, x.address(), v.address(), target.address(), weights.address(), chunk, width, time,
                    guidance_weight);
    launched("rtc_guide");
  }
  std::pair<double, double> change_norms(Ptr<const float> v, Ptr<const float> prev, int64_t chunk, int64_t width,
                                         int64_t action_dim) override {
    cuda::change_norms(stream_, v.address(), prev.address(), chunk, width, action_dim, sums_.at().address());
    launched("change_norms");
    double sums[2];
    download(Ptr<const void>(sums_.at().address()), sizeof sums, sums);
    return {sums[0], sums[1]};
  }

 protected:
  std::shared_ptr<void> allocate_bytes(std::size_t bytes) override {
    auto p = pool_.allocate(bytes);
    if (!p) {
      std::size_t free_bytes = 0, total_bytes = 0;
      cudaMemGetInfo(&free_bytes, &total_bytes);
      const auto s = pool_.stats();
      throw Error(ErrorCode::unavailable,
                  std::string("cuda: out of device memory on ") + props_.name + ": " + mib(bytes) + " more needed (" +
                      mib(s.in_use) + " held by this model), " + mib(free_bytes) + " free of " + mib(total_bytes));
    }
    return p;
  }

 private:
  static constexpr std::size_t kWorkspaceBytes = std::size_t(32) << 20;  // cuBLASLt's recommendation for Hopper

  static void require(bool ok, const char* message) {
    if (!ok) throw Error(ErrorCode::invalid_argument, message);
  }
  static cuda_math::Act to_math(Activation a) {
    switch (a) {
      case Activation::silu: return cuda_math::Act::silu;
      case Activation::gelu_tanh: return cuda_math::Act::gelu_tanh;
      case Activation::gelu_erf: return cuda_math::Act::gelu_erf;
      case Activation::relu: return cuda_math::Act::relu;
    }
    return cuda_math::Act::silu;
  }
  // A launch error (bad configuration, no image for this device) shows at once; faults inside a kernel show at the
  // next synchronisation.
  static void launched(const char* op) { check(cudaGetLastError(), op); }

  void copy_in(const void* host, std::size_t bytes, void* device) {
    check(cudaMemcpyAsync(device, host, bytes, cudaMemcpyHostToDevice, stream_), "upload");
    synchronize();  // the host copy (a converted weight) may go away when the caller returns
  }
  // Scratch that grows to the largest request and then stays.
  struct Scratch {
    std::shared_ptr<void> memory;
    std::size_t size = 0;
    void* get() const { return memory.get(); }
  };
  void ensure(Scratch& scratch, std::size_t bytes) {
    if (scratch.size >= bytes) return;
    scratch.memory.reset();
    scratch.memory = allocate_bytes(bytes);
    scratch.size = bytes;
  }

  void gemm(const void* w, const void* x, StoredType type, int64_t m, int64_t n, int64_t k, float* y, int64_t ldy,
            const float* bias, bool accumulate) {
    const int align = std::min({alignment(w, k * int64_t(stored_size(type))), alignment(x, k * int64_t(stored_size(type))),
                                alignment(y, ldy * 4)});
    const GemmKey key{m, n, k, ldy, type, accumulate, bias != nullptr, align};
    GemmPlan& plan = plan_for(key);
    if (bias)
      check(cublasLtMatmulDescSetAttribute(plan.desc, CUBLASLT_MATMUL_DESC_BIAS_POINTER, &bias, sizeof bias),
            "bias pointer");
    const float one = 1.0f, beta = accumulate ? 1.0f : 0.0f;
    check(cublasLtMatmul(lt_, plan.desc, &one, w, plan.a, x, plan.b, &beta, y, plan.c, y, plan.c, &plan.algo,
                         workspace_.get(), kWorkspaceBytes, stream_),
          "cublasLtMatmul");
  }

  GemmPlan& plan_for(const GemmKey& key) {
    auto it = plans_.find(key);
    if (it != plans_.end()) return *it->second;
    auto plan = std::make_unique<GemmPlan>();
    // fp32 products accumulate in true fp32 (CUBLAS_COMPUTE_32F never uses TF32); half types on tensor cores with
    // fp32 accumulation and fp32 output.
    check(cublasLtMatmulDescCreate(&plan->desc, CUBLAS_COMPUTE_32F, CUDA_R_32F), "matmul descriptor");
    const cublasOperation_t transpose = CUBLAS_OP_T, plain = CUBLAS_OP_N;
    check(cublasLtMatmulDescSetAttribute(plan->desc, CUBLASLT_MATMUL_DESC_TRANSA, &transpose, sizeof transpose), "transa");
    check(cublasLtMatmulDescSetAttribute(plan->desc, CUBLASLT_MATMUL_DESC_TRANSB, &plain, sizeof plain), "transb");
    if (key.bias) {
      const cublasLtEpilogue_t epilogue = CUBLASLT_EPILOGUE_BIAS;
      const cudaDataType_t bias_type = CUDA_R_32F;
      check(cublasLtMatmulDescSetAttribute(plan->desc, CUBLASLT_MATMUL_DESC_EPILOGUE, &epilogue, sizeof epilogue),
            "epilogue");
      check(cublasLtMatmulDescSetAttribute(plan->desc, CUBLASLT_MATMUL_DESC_BIAS_DATA_TYPE, &bias_type,
                                           sizeof bias_type),
            "bias type");
    }
    const cudaDataType_t t = cuda_type(key.type);
    check(cublasLtMatrixLayoutCreate(&plan->a, t, uint64_t(key.k), uint64_t(key.n), key.k), "layout A");
    check(cublasLtMatrixLayoutCreate(&plan->b, t, uint64_t(key.k), uint64_t(key.m), key.k), "layout B");
    check(cublasLtMatrixLayoutCreate(&plan->c, CUDA_R_32F, uint64_t(key.n), uint64_t(key.m), key.ldy), "layout C");

    cublasLtMatmulPreference_t pref = nullptr;
    check(cublasLtMatmulPreferenceCreate(&pref), "preference");
    const uint64_t workspace = kWorkspaceBytes;
    const uint32_t align = uint32_t(key.align);
    cublasLtMatmulPreferenceSetAttribute(pref, CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES, &workspace, sizeof workspace);
    for (auto attr : {CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_A_BYTES, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_B_BYTES,
                      CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_C_BYTES, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_D_BYTES})
      cublasLtMatmulPreferenceSetAttribute(pref, attr, &align, sizeof align);
    cublasLtMatmulHeuristicResult_t result{};
    int found = 0;
    const cublasStatus_t status =
        cublasLtMatmulAlgoGetHeuristic(lt_, plan->desc, plan->a, plan->b, plan->c, plan->c, pref, 1, &result, &found);
    cublasLtMatmulPreferenceDestroy(pref);
    if (status != CUBLAS_STATUS_SUCCESS || found == 0)
      throw Error(ErrorCode::unsupported, "cuda: cuBLASLt has no algorithm for a " + std::to_string(key.m) + " x " +
                                              std::to_string(key.n) + " x " + std::to_string(key.k) + " product");
    plan->algo = result.algo;
    return *plans_.emplace(key, std::move(plan)).first->second;
  }

  cuda::DevicePool pool_;
  cudaDeviceProp props_{};
  cudaStream_t stream_ = nullptr;
  cublasLtHandle_t lt_ = nullptr;
  std::shared_ptr<void> workspace_;
  Scratch half_input_, patch_cols_, rope_table_;
  Array<double> sums_;
  std::vector<int64_t> ids_host_;
  std::map<GemmKey, std::unique_ptr<GemmPlan>> plans_;
};

}  // namespace

bool cuda_usable(std::string* why) {
  int count = 0;
  const cudaError_t status = cudaGetDeviceCount(&count);
  if (status != cudaSuccess || count == 0) {
    cudaGetLastError();
    if (why) {
      // With no driver at all the runtime says its version is "insufficient"; name the real cause instead.
      void* driver = dlopen("libcuda.so.1", RTLD_LAZY | RTLD_LOCAL);
      const std::string cause = !driver ? "no NVIDIA driver: libcuda.so.1 not found"
                                : status != cudaSuccess ? cudaGetErrorString(status)
                                                        : "the driver reports no devices";
      if (driver) dlclose(driver);
      *why = "backend 'cuda': no usable CUDA device (" + cause + ")";
    }
    return false;
  }
  std::string missing;
  if (!cuda::kernels_loadable(&missing)) {
    if (why) *why = "backend 'cuda': " + missing;
    return false;
  }
  return true;
}

std::shared_ptr<Backend> make_cuda_backend() {
  std::string why;
  if (!cuda_usable(&why)) throw Error(ErrorCode::unavailable, why);
  return std::make_shared<CudaBackend>();
}

}  // namespace tether::backend
