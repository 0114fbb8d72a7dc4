// Loading, warm-up and the health state machine of the served model.
#include "serve/model_host.h"

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "core/error.h"
#include "serve/http_error.h"

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
                     Metrics& metrics, std::string embodiment, std::string metric_labels)
    : loader_(std::move(loader)),
      embodiment_(std::move(embodiment)),
      metric_labels_(std::move(metric_labels)),
      batch_options_(batch),
      metrics_(metrics),
      wedges_(std::move(wedge_options)) {}

std::string ModelHost::embodiment() const {
  if (!embodiment_.empty() || !loaded()) return embodiment_;
  return engine_->spec.embodiment;
}

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
    register_wedge_metrics(metrics_, wedges_, metric_labels_);
    engine_ = std::move(e);
    batcher_ = std::move(b);
    state_.store(HealthState::warming, std::memory_order_release);
    const std::string tag = engine_->spec.embodiment.empty() ? "" : ", embodiment " + engine_->spec.embodiment;
    std::fprintf(stderr, "tether serve: model loaded (%s%s, %s); warming up\n", engine_->spec.family.c_str(),
                 tag.c_str(), engine_->model_hash.c_str());
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

namespace {

runtime::WedgeOptions host_wedges(const runtime::WedgeOptions& wedges, const std::string& embodiment, bool several) {
  runtime::WedgeOptions w = wedges;
  // One hash chain per recorder: hosts sharing a directory would interleave two chains in one file.
  if (several && w.record) w.record->dir = (std::filesystem::path(w.record->dir) / embodiment).string();
  return w;
}

// How far from serving a state is: the worst one speaks for a set of hosts.
int unreadiness(HealthState s) {
  switch (s) {
    case HealthState::failed: return 5;
    case HealthState::loading: return 4;
    case HealthState::warming: return 3;
    case HealthState::circuit_open: return 2;
    case HealthState::degraded: return 1;
    case HealthState::ready: return 0;
  }
  return 5;
}

}  // namespace

ModelHosts::ModelHosts(std::vector<HostLoader> loaders, runtime::BatcherOptions batch,
                       const runtime::WedgeOptions& wedges, Metrics& metrics) {
  if (loaders.empty()) throw Error(ErrorCode::invalid_argument, "no model to serve");
  const bool several = loaders.size() > 1;
  for (auto& l : loaders) {
    if (several && l.embodiment.empty())
      throw Error(ErrorCode::invalid_argument, "serving several embodiments: each needs its tag");
    for (const auto& h : hosts_)
      if (h->embodiment() == l.embodiment)
        throw Error(ErrorCode::invalid_argument, "embodiment '" + l.embodiment + "' is named twice");
    // Each host's wedge counters and gauges are series of their own, by embodiment.
    std::string labels = several ? "embodiment=\"" + escape_label(l.embodiment) + "\"" : "";
    runtime::WedgeOptions own = host_wedges(l.wedges ? *l.wedges : wedges, l.embodiment, several);
    hosts_.push_back(std::make_unique<ModelHost>(std::move(l.load), batch, std::move(own), metrics, l.embodiment,
                                                 std::move(labels)));
  }
}

ModelHost& ModelHosts::route(const std::string& embodiment) {
  if (embodiment.empty()) return primary();
  for (auto& h : hosts_)
    if (h->embodiment() == embodiment) return *h;
  std::string served;
  for (const auto& tag : embodiments())
    if (!tag.empty()) served += (served.empty() ? "" : ", ") + tag;
  throw HttpError(400, "unknown_embodiment",
                  "unknown embodiment tag '" + embodiment + "' (" +
                      (served.empty() ? std::string("this server's model has no embodiment tags")
                                      : "this server serves: " + served) +
                      ")");
}

std::vector<std::string> ModelHosts::embodiments() const {
  std::vector<std::string> out;
  for (const auto& h : hosts_) out.push_back(h->embodiment());
  return out;
}

bool ModelHosts::load() {
  for (auto& h : hosts_)
    if (!h->load()) return false;
  return true;
}

void ModelHosts::stop() {
  for (auto& h : hosts_) h->stop();
}

HealthState ModelHosts::health() const {
  HealthState worst = HealthState::ready;
  for (const auto& h : hosts_) {
    const HealthState s = h->health();
    if (unreadiness(s) > unreadiness(worst)) worst = s;
  }
  return worst;
}

std::exception_ptr ModelHosts::load_error() const {
  for (const auto& h : hosts_)
    if (h->load_error()) return h->load_error();
  return nullptr;
}

Json inference_mode_json(const Engine& engine) {
  return {{"backend", engine.backend}, {"precision", engine.precision}, {"compute", engine.compute}, {"gemm", engine.gemm}};
}

}  // namespace tether::serve
