// Loading, warm-up and the health state machine of the served model.
#include "serve/model_host.h"

#include <chrono>
#include <cstdio>

#include "runtime/fault_injection.h"
#include "serve/wedge_metrics.h"

namespace tether::serve {

namespace {

// Consecutive failed forward passes after which /health reports degraded (one bad batch is not a sick server).
constexpr int kDegradedAfterFailures = 3;

using Clock = std::chrono::steady_clock;

}  // namespace

const char* health_state_name(HealthState s) {
  switch (s) {
    case HealthState::loading: return "loading";
    case HealthState::warming: return "warming";
    case HealthState::ready: return "ready";
    case HealthState::degraded: return "degraded";
    case HealthState::failed: return "failed";
    case HealthState::circuit_open: return "circuit_open";
  }
  return "unknown";
}

ModelHost::ModelHost(EngineLoader loader, runtime::BatcherOptions batch, runtime::WedgeOptions wedge_options,
                     Metrics& metrics)
    : loader_(std::move(loader)), batch_options_(batch), metrics_(metrics), wedges_(std::move(wedge_options)) {}

ModelHost::~ModelHost() { stop(); }

void ModelHost::stop() {
  if (batcher_) batcher_->stop();
}

bool ModelHost::load() {
  try {
    auto e = std::make_unique<Engine>(loader_());
    wedges_.bind_model(e->spec, e->actions_normalized);
    const auto& w = wedges_.options();
    auto b = std::make_unique<runtime::Batcher>(
        runtime::with_injected_faults(e->predict, w.inject_latency_ms, w.inject_failure_file), batch_options_);
    metrics_.set_gemm(e->gemm);
    metrics_.declare_stages(e->spec.stages);
    register_wedge_metrics(metrics_, wedges_);
    engine_ = std::move(e);
    batcher_ = std::move(b);
    state_.store(HealthState::warming, std::memory_order_release);
    std::fprintf(stderr, "tether serve: model loaded (%s, %s); warming up\n", engine_->spec.family.c_str(),
                 engine_->model_hash.c_str());
    for (const auto& warning : engine_->load_warnings)
      std::fprintf(stderr, "tether serve: warning: %s\n", warning.c_str());
    try {
      const auto t0 = Clock::now();
      batcher_->submit(policy::synthetic_observation(engine_->spec), Clock::time_point::max()).get();
      std::fprintf(stderr, "tether serve: ready (warm-up %.1f ms)\n",
                   std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
      state_.store(HealthState::ready, std::memory_order_release);
    } catch (const std::exception& ex) {
      std::fprintf(stderr, "tether serve: warm-up inference failed: %s\n", ex.what());
      state_.store(HealthState::degraded, std::memory_order_release);
    }
    metrics_.set_model_ready(state_.load() == HealthState::ready);
    return true;
  } catch (...) {
    load_error_ = std::current_exception();
    state_.store(HealthState::failed, std::memory_order_release);
    return false;
  }
}

HealthState ModelHost::health() const {
  const HealthState s = model_state();
  if ((s == HealthState::ready || s == HealthState::degraded) &&
      wedges_.breaker().state() != runtime::CircuitBreaker::State::closed)
    return HealthState::circuit_open;
  return s;
}

HealthState ModelHost::model_state() const {
  const HealthState s = state_.load(std::memory_order_acquire);
  if (s != HealthState::ready && s != HealthState::degraded) return s;
  const int failures = batcher_->consecutive_failures();
  if (failures >= kDegradedAfterFailures) return HealthState::degraded;
  // A failed warm-up is forgiven by the first forward pass that succeeds after it.
  if (s == HealthState::degraded && failures == 0 && batcher_->batches_run() > 1) return HealthState::ready;
  return s;
}

bool ModelHost::loaded() const {
  const HealthState s = state_.load(std::memory_order_acquire);
  return s == HealthState::warming || s == HealthState::ready || s == HealthState::degraded;
}

bool ModelHost::serving() const {
  const HealthState s = model_state();
  return s == HealthState::ready || s == HealthState::degraded;
}

Json inference_mode_json(const Engine& engine) {
  return {{"backend", engine.backend}, {"precision", engine.precision}, {"compute", engine.compute}, {"gemm", engine.gemm}};
}

}  // namespace tether::serve
