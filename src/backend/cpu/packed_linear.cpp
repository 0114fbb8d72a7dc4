// Packing linear weights once and running them through oneDNN or the panel GEMM (see packed_linear.h).
#include "backend/cpu/packed_linear.h"

#include <algorithm>
#include <cstring>
#include <map>
#include <utility>
#include <oneapi/dnnl/dnnl.hpp>
#include <string>
#include <vector>

#include "backend/cpu/cpu_features.h"
#include "backend/cpu/panel_gemm.h"
#include "core/dtype.h"
#include "core/error.h"

namespace tether::cpu {

namespace {

using dnnl::memory;
using dt = memory::data_type;
using tag = memory::format_tag;

dnnl::engine& cpu_engine() {
  // cpu_paths() first: it applies the ISA cap, which oneDNN reads before its first primitive.
  static dnnl::engine engine = (cpu_paths(), dnnl::engine(dnnl::engine::kind::cpu, 0));
  return engine;
}

dnnl::stream& cpu_stream() {
  static dnnl::stream stream(cpu_engine());
  return stream;
}

// The packed layout is chosen by a primitive for this many rows; primitives for other row counts then read
// the same layout (oneDNN's blocked matmul weight formats do not depend on M).
constexpr int64_t kLayoutRows = 64;

}  // namespace

const char* precision_name(Precision p) {
  return p == Precision::bf16 ? "bf16" : p == Precision::fp16 ? "fp16" : "fp32";
}

Precision parse_precision(const std::string& name) {
  for (Precision p : {Precision::fp32, Precision::bf16, Precision::fp16})
    if (name == precision_name(p)) return p;
  throw Error(ErrorCode::invalid_argument, "precision '" + name + "' is not one of fp32, bf16, fp16");
}

LinearPath linear_path(Precision precision) {
  switch (precision) {
    case Precision::fp32: return cpu_paths().fp32_panel ? LinearPath::panel_f32 : LinearPath::onednn_f32;
    case Precision::bf16: return cpu_paths().native_bf16 ? LinearPath::onednn_bf16 : LinearPath::panel_bf16;
    case Precision::fp16: return LinearPath::panel_f16;  // oneDNN 2.6 has no f16 matmul below AVX512-FP16
  }
  return LinearPath::onednn_f32;
}

const char* compute_mode(Precision precision) {
  switch (linear_path(precision)) {
    case LinearPath::onednn_f32:
    case LinearPath::panel_f32: return "fp32";
    case LinearPath::onednn_bf16: return "bf16";
    case LinearPath::panel_bf16: return "bf16-weights";
    case LinearPath::panel_f16: return "fp16-weights";
  }
  return "?";
}

std::string gemm_name(Precision precision) {
  const LinearPath path = linear_path(precision);
  if (path == LinearPath::onednn_f32 || path == LinearPath::onednn_bf16) return "onednn";
  return std::string("panel-") + detail::panel_kernel().name;
}

std::string compute_mode_description(Precision precision) {
  const CpuPaths& c = cpu_paths();
  const std::string kernel = detail::panel_kernel().name;
  switch (linear_path(precision)) {
    case LinearPath::onednn_f32: return "fp32 GEMM (oneDNN " + c.onednn_isa + ")";
    case LinearPath::panel_f32: return "fp32 GEMM (" + kernel + " panel kernel, batch-invariant)";
    case LinearPath::onednn_bf16:
      return "native bf16 GEMM (oneDNN " + c.onednn_isa + "): bf16 weights and inputs, fp32 accumulation";
    case LinearPath::panel_bf16:
      return "bf16 weights widened to fp32 in the kernel (" + kernel + "): " + bf16_widened_reason() +
             "; inputs and accumulation in fp32";
    case LinearPath::panel_f16:
      return "fp16 weights widened to fp32 in the kernel (" + kernel + "); inputs and accumulation in fp32";
  }
  return "?";
}

struct PackedLinear::Impl {
  int64_t n = 0, k = 0;
  Precision precision = Precision::fp32;
  LinearPath path = LinearPath::onednn_f32;
  memory weights, bias;  // oneDNN paths
  // Panel GEMM path: panels in the weight dtype, the bias zero-padded to whole panels.
  PanelBuffer<uint16_t> panels;
  PanelBuffer<float> panels_f32;
  std::vector<float> panel_bias;
  detail::PanelGemmFn panel_fn = nullptr;

  bool onednn() const { return path == LinearPath::onednn_f32 || path == LinearPath::onednn_bf16; }
  void pack_panels(const float* weight, const float* bias_in);
  struct Plan {
    dnnl::primitive prim;
    std::string kernel;  // oneDNN's implementation name
    memory src, dst, scratchpad;
  };
  mutable std::map<std::pair<int64_t, bool>, Plan> plans;  // (rows, accumulate) -> primitive
  mutable std::vector<uint16_t> x_bf16;                     // bf16 copy of the input rows
  mutable std::vector<float> y_dense;                       // the result rows, where the caller's are strided

  dt src_type() const { return path == LinearPath::onednn_bf16 ? dt::bf16 : dt::f32; }

  dnnl::matmul::primitive_desc describe(int64_t m, const memory::desc& weights_md, bool accumulate) const {
    const memory::desc src_md({m, k}, src_type(), tag::ab);
    const memory::desc dst_md({m, n}, dt::f32, tag::ab);
    const memory::desc bias_md({1, n}, dt::f32, tag::ab);
    dnnl::primitive_attr attr;
    attr.set_scratchpad_mode(dnnl::scratchpad_mode::user);
    if (accumulate) {
      dnnl::post_ops ops;
      ops.append_sum(1.0f);
      attr.set_post_ops(ops);
    }
    return dnnl::matmul::primitive_desc(dnnl::matmul::desc(src_md, weights_md, bias_md, dst_md), attr, cpu_engine());
  }

  const Plan& plan(int64_t m, bool accumulate) const {
    auto it = plans.find({m, accumulate});
    if (it != plans.end()) return it->second;
    Plan p;
    try {
      const auto pd = describe(m, weights.get_desc(), accumulate);
      p.prim = dnnl::matmul(pd);
      p.kernel = pd.impl_info_str();
      p.src = memory(pd.src_desc(), cpu_engine(), DNNL_MEMORY_NONE);
      p.dst = memory(pd.dst_desc(), cpu_engine(), DNNL_MEMORY_NONE);
      p.scratchpad = memory(pd.scratchpad_desc(), cpu_engine());
    } catch (const dnnl::error& e) {
      throw Error(ErrorCode::internal, "PackedLinear: oneDNN has no matmul for " + std::to_string(m) + " x [" +
                                           std::to_string(n) + ", " + std::to_string(k) + "]: " + e.what());
    }
    return plans.emplace(std::make_pair(m, accumulate), std::move(p)).first->second;
  }

  // oneDNN 2.6's AVX-512 and AMX matmul kernels (brgemm) take only a dense result: with a row stride wider than the
  // row it falls back to its reference kernel, 10 to 100 times slower. So every plan writes dense rows, and forward
  // copies them out where the caller's are strided.
  const Plan& plan_for(int64_t m, bool accumulate, int64_t /*ldy*/) const { return plan(m, accumulate); }
};

PackedLinear::PackedLinear() = default;
PackedLinear::~PackedLinear() = default;
PackedLinear::PackedLinear(PackedLinear&&) noexcept = default;
PackedLinear& PackedLinear::operator=(PackedLinear&&) noexcept = default;

namespace {
// Every value is a bfloat16 value (its low 16 bits are zero): what a bf16 checkpoint widened to float32 holds.
bool exactly_bf16(const float* w, int64_t count) {
  for (int64_t i = 0; i < count; ++i) {
    uint32_t bits;
    std::memcpy(&bits, &w[i], sizeof bits);
    if (bits & 0xFFFFu) return false;
  }
  return true;
}
}  // namespace

void PackedLinear::Impl::pack_panels(const float* weight, const float* bias_in) {
  const detail::PanelKernel& kernel = detail::panel_kernel();
  auto type = path == LinearPath::panel_bf16  ? detail::PanelType::bf16
              : path == LinearPath::panel_f16 ? detail::PanelType::f16
                                              : detail::PanelType::f32;
  // fp32 weights that are all bf16 values (a bf16 checkpoint) are kept as bf16 panels: the kernel widens them back
  // exactly, so every product is bit-identical to the float32 panels' while the weights take half the memory.
  if (type == detail::PanelType::f32 && exactly_bf16(weight, n * k)) type = detail::PanelType::bf16;
  panel_fn = kernel.get(type);
  if (type == detail::PanelType::f32) panels_f32 = detail::pack_f32_panels(weight, n, k, kernel.panel_width);
  else panels = detail::pack_half_panels(weight, n, k, kernel.panel_width, type);
  panel_bias = detail::pad_bias(bias_in, n, kernel.panel_width);
}

LinearPath PackedLinear::path() const { return impl_ ? impl_->path : LinearPath::onednn_f32; }
std::string PackedLinear::kernel(int64_t m, bool accumulate, int64_t ldy) const {
  if (!impl_) throw Error(ErrorCode::internal, "PackedLinear: kernel before pack");
  if (!impl_->onednn()) return std::string("panel-") + detail::panel_kernel().name;
  return impl_->plan_for(m, accumulate, ldy == 0 ? impl_->n : ldy).kernel;
}
int64_t PackedLinear::n() const { return impl_ ? impl_->n : 0; }
int64_t PackedLinear::k() const { return impl_ ? impl_->k : 0; }

void PackedLinear::pack(const float* weight, int64_t n, int64_t k, const float* bias, Precision precision) {
  if (n <= 0 || k <= 0) throw Error(ErrorCode::invalid_argument, "PackedLinear: empty weight");
  auto impl = std::make_unique<Impl>();
  impl->n = n;
  impl->k = k;
  impl->precision = precision;
  impl->path = linear_path(precision);
  if (!impl->onednn()) {
    impl->pack_panels(weight, bias);
    impl_ = std::move(impl);
    return;
  }
  try {
    // W is [n, k] row-major, i.e. the matmul's [k, n] weights with strides (1, k): format "ba".
    const memory::desc user_md({k, n}, dt::f32, tag::ba);
    memory user(user_md, cpu_engine(), const_cast<float*>(weight));
    const memory::desc any_md({k, n}, impl->src_type(), tag::any);
    const auto pd = impl->describe(kLayoutRows, any_md, false);
    impl->weights = memory(pd.weights_desc(), cpu_engine());
    dnnl::reorder(user, impl->weights).execute(cpu_stream(), user, impl->weights);
    impl->bias = memory(memory::desc({1, n}, dt::f32, tag::ab), cpu_engine());
    float* b = static_cast<float*>(impl->bias.get_data_handle());
    for (int64_t i = 0; i < n; ++i) b[i] = bias ? bias[i] : 0.0f;
    cpu_stream().wait();
  } catch (const dnnl::error& e) {
    throw Error(ErrorCode::internal, std::string("PackedLinear: oneDNN could not pack a [") + std::to_string(n) +
                                         ", " + std::to_string(k) + "] weight: " + e.what());
  }
  impl_ = std::move(impl);
}

void PackedLinear::forward(const float* x, int64_t m, float* y, bool accumulate, int64_t ldy) const {
  if (!impl_) throw Error(ErrorCode::internal, "PackedLinear: forward before pack");
  if (m <= 0) return;
  const Impl& w = *impl_;
  if (ldy == 0) ldy = w.n;
  if (ldy < w.n) throw Error(ErrorCode::internal, "PackedLinear: output stride smaller than the row");
  if (!w.onednn()) {
    const void* panels = w.panels_f32.empty() ? static_cast<const void*>(w.panels.data()) : w.panels_f32.data();
    w.panel_fn({x, m, w.k, w.k, panels, w.n, w.panel_bias.data(), y, ldy, accumulate});
    return;
  }
  const Impl::Plan& p = w.plan_for(m, accumulate, ldy);
  const void* src = x;
  if (w.path == LinearPath::onednn_bf16) {
    if (w.x_bf16.size() < std::size_t(m * w.k)) w.x_bf16.resize(std::size_t(m * w.k));
    uint16_t* dst = w.x_bf16.data();
    const int64_t total = m * w.k;
#pragma omp parallel for if (total > (1 << 16))
    for (int64_t i = 0; i < total; ++i) dst[i] = f32_to_bf16(x[i]);
    src = dst;
  }
  const bool strided = ldy != w.n;
  float* out = y;
  if (strided) {
    if (w.y_dense.size() < std::size_t(m * w.n)) w.y_dense.resize(std::size_t(m * w.n));
    out = w.y_dense.data();
    if (accumulate)
      for (int64_t r = 0; r < m; ++r) std::memcpy(out + r * w.n, y + r * ldy, sizeof(float) * std::size_t(w.n));
  }
  p.src.set_data_handle(const_cast<void*>(src));
  p.dst.set_data_handle(out);
  // The C entry point takes the arguments as a plain array: no container is built per call.
  const dnnl_exec_arg_t args[] = {{DNNL_ARG_SRC, p.src.get()},
                                  {DNNL_ARG_WEIGHTS, w.weights.get()},
                                  {DNNL_ARG_BIAS, w.bias.get()},
                                  {DNNL_ARG_DST, p.dst.get()},
                                  {DNNL_ARG_SCRATCHPAD, p.scratchpad.get()}};
  const dnnl_status_t st = dnnl_primitive_execute(p.prim.get(), cpu_stream().get(), 5, args);
  if (st != dnnl_success)
    throw Error(ErrorCode::internal, "PackedLinear: oneDNN matmul failed with status " + std::to_string(int(st)));
  if (strided)
    for (int64_t r = 0; r < m; ++r) std::memcpy(y + r * ldy, out + r * w.n, sizeof(float) * std::size_t(w.n));
}

}  // namespace tether::cpu
