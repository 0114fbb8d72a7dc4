#include "backend/cpu/packed_linear.h"

#include <map>
#include <tuple>
#include <oneapi/dnnl/dnnl.hpp>
#include <string>
#include <vector>

#include "core/dtype.h"
#include "core/error.h"

namespace tether::cpu {

namespace {

using dnnl::memory;
using dt = memory::data_type;
using tag = memory::format_tag;

dnnl::engine& cpu_engine() {
  static dnnl::engine engine(dnnl::engine::kind::cpu, 0);
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

const char* precision_name(Precision p) { return p == Precision::bf16 ? "bf16" : "fp32"; }

struct PackedLinear::Impl {
  int64_t n = 0, k = 0;
  Precision precision = Precision::fp32;
  memory weights, bias;
  struct Plan {
    dnnl::primitive prim;
    memory src, dst, scratchpad;
  };
  mutable std::map<std::tuple<int64_t, bool, int64_t>, Plan> plans;  // (rows, accumulate, ldy) -> primitive
  mutable std::vector<uint16_t> x_bf16;                    // bf16 copy of the input rows

  dt src_type() const { return precision == Precision::bf16 ? dt::bf16 : dt::f32; }

  dnnl::matmul::primitive_desc describe(int64_t m, const memory::desc& weights_md, bool accumulate,
                                        int64_t ldy) const {
    const memory::desc src_md({m, k}, src_type(), tag::ab);
    const memory::desc dst_md({m, n}, dt::f32, memory::dims{ldy, 1});
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

  const Plan& plan(int64_t m, bool accumulate, int64_t ldy) const {
    auto it = plans.find({m, accumulate, ldy});
    if (it != plans.end()) return it->second;
    const auto pd = describe(m, weights.get_desc(), accumulate, ldy);
    Plan p;
    p.prim = dnnl::matmul(pd);
    p.src = memory(pd.src_desc(), cpu_engine(), DNNL_MEMORY_NONE);
    p.dst = memory(pd.dst_desc(), cpu_engine(), DNNL_MEMORY_NONE);
    p.scratchpad = memory(pd.scratchpad_desc(), cpu_engine());
    return plans.emplace(std::make_tuple(m, accumulate, ldy), std::move(p)).first->second;
  }
};

PackedLinear::PackedLinear() = default;
PackedLinear::~PackedLinear() = default;
PackedLinear::PackedLinear(PackedLinear&&) noexcept = default;
PackedLinear& PackedLinear::operator=(PackedLinear&&) noexcept = default;

int64_t PackedLinear::n() const { return impl_ ? impl_->n : 0; }
int64_t PackedLinear::k() const { return impl_ ? impl_->k : 0; }

void PackedLinear::pack(const float* weight, int64_t n, int64_t k, const float* bias, Precision precision) {
  if (n <= 0 || k <= 0) throw Error(ErrorCode::invalid_argument, "PackedLinear: empty weight");
  auto impl = std::make_unique<Impl>();
  impl->n = n;
  impl->k = k;
  impl->precision = precision;
  try {
    // W is [n, k] row-major, i.e. the matmul's [k, n] weights with strides (1, k): format "ba".
    const memory::desc user_md({k, n}, dt::f32, tag::ba);
    memory user(user_md, cpu_engine(), const_cast<float*>(weight));
    const memory::desc any_md({k, n}, impl->src_type(), tag::any);
    const auto pd = impl->describe(kLayoutRows, any_md, false, n);
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
  const Impl::Plan& p = w.plan(m, accumulate, ldy);
  const void* src = x;
  if (w.precision == Precision::bf16) {
    if (w.x_bf16.size() < std::size_t(m * w.k)) w.x_bf16.resize(std::size_t(m * w.k));
    uint16_t* dst = w.x_bf16.data();
    const int64_t total = m * w.k;
#pragma omp parallel for if (total > (1 << 16))
    for (int64_t i = 0; i < total; ++i) dst[i] = f32_to_bf16(x[i]);
    src = dst;
  }
  p.src.set_data_handle(const_cast<void*>(src));
  p.dst.set_data_handle(y);
  // The C entry point takes the arguments as a plain array: no container is built per call.
  const dnnl_exec_arg_t args[] = {{DNNL_ARG_SRC, p.src.get()},
                                  {DNNL_ARG_WEIGHTS, w.weights.get()},
                                  {DNNL_ARG_BIAS, w.bias.get()},
                                  {DNNL_ARG_DST, p.dst.get()},
                                  {DNNL_ARG_SCRATCHPAD, p.scratchpad.get()}};
  const dnnl_status_t st = dnnl_primitive_execute(p.prim.get(), cpu_stream().get(), 5, args);
  if (st != dnnl_success)
    throw Error(ErrorCode::internal, "PackedLinear: oneDNN matmul failed with status " + std::to_string(int(st)));
}

}  // namespace tether::cpu
