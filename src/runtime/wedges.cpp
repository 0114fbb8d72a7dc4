// Synchronous wedge logic and per-episode bookkeeping (see wedges.h for the order).
#include "runtime/wedges.h"

#include <cmath>

#include "core/error.h"

namespace tether::runtime {

const char* action_source_name(ActionSource s) {
  switch (s) {
    case ActionSource::model: return "model";
    case ActionSource::cache: return "cache";
    case ActionSource::last_good: return "last_good";
    case ActionSource::fallback: return "fallback";
  }
  return "unknown";
}

Wedges::Wedges(WedgeOptions options)
    : opts_(std::move(options)),
      breaker_(opts_.max_consecutive_crashes, std::chrono::milliseconds(opts_.circuit_reset_ms)),
      episodes_(opts_.max_episodes) {
  // The most specific source wins: the flag, then the safety file (it overrides the preset), then the embodiment.
  if (opts_.control_rate_hz > 0) rate_hz_ = opts_.control_rate_hz;
  else if (opts_.safety && opts_.safety->control_rate_hz) rate_hz_ = *opts_.safety->control_rate_hz;
  else if (opts_.embodiment) rate_hz_ = opts_.embodiment->control_rate_hz;
  if (opts_.record) recorder_ = std::make_unique<TraceRecorder>(*opts_.record);
}

int64_t embodiment_action_dim(const policy::Embodiment& e, const models::ModelSpec& spec) {
  const int64_t joints = int64_t(e.joints.size()), dim = spec.action_dim;
  if (joints == dim) return dim;
  const bool padded = spec.max_action_dim > 0 && dim == spec.max_action_dim && joints < dim;
  if (padded) return joints;
  throw Error(ErrorCode::invalid_argument,
              "embodiment '" + e.name + "' has " + std::to_string(joints) + " joints, the model outputs " +
                  std::to_string(dim) + " action values" +
                  (joints < dim ? " (only a padded output, action_dim = max_action_dim " +
                                      std::to_string(spec.max_action_dim) + ", is cut to fewer joints)"
                                : ""));
}

void Wedges::bind_model(const models::ModelSpec& spec, bool actions_normalized) {
  rows_ = spec.chunk_size;
  dim_ = model_dim_ = spec.action_dim;
  model_embodiment_ = spec.embodiment;
  std::vector<policy::JointLimits> limits;
  if (opts_.embodiment) {
    const auto& e = *opts_.embodiment;
    dim_ = embodiment_action_dim(e, spec);
    // RTC guides the model's whole output with the client's leftover; a cut one has lost the padded values.
    if (dim_ != model_dim_ && opts_.sampler.rtc)
      throw Error(ErrorCode::invalid_argument, "--rtc: embodiment '" + e.name + "' keeps " + std::to_string(dim_) +
                                                   " of the model's " + std::to_string(model_dim_) +
                                                   " action values, and RTC needs all of them back");
    joints_ = e.joints;
    limits = e.limits;
    map_to_range_ = actions_normalized;
  } else {
    for (int64_t j = 0; j < dim_; ++j) joints_.push_back("joint_" + std::to_string(j));
    limits.resize(std::size_t(dim_));
  }
  if (opts_.safety) limits = policy::apply_safety_config(*opts_.safety, joints_, std::move(limits));
  if (opts_.embodiment || opts_.safety) {
    guard_.emplace(joints_, limits, rate_hz_);
    if (opts_.audit_log.empty()) throw Error(ErrorCode::invalid_argument, "the action guard needs an audit log path");
    audit_ = std::make_unique<AuditLog>(opts_.audit_log);
  }
}

std::optional<std::vector<float>> Wedges::try_skip(Episode& ep, const policy::Observation& obs,
                                                   const std::vector<float>& normalized_state, WedgeReport& report) {
  if (!skip_enabled()) return std::nullopt;
  std::lock_guard lock(ep.mu);
  EpisodeState& s = ep.state;
  if (s.last_good.empty()) return std::nullopt;
  report.similarity_distance = observation_distance(obs, normalized_state, s);
  if (!(report.similarity_distance <= opts_.similarity_threshold) || s.similar_skips >= opts_.max_similar_skips)
    return std::nullopt;
  ++s.similar_skips;
  report.skipped = true;
  report.similar_skips = s.similar_skips;
  report.source = ActionSource::cache;
  report.advanced_steps = elapsed_steps(s.last_good.time, SteadyClock::now(), rate_hz_);
  return advance_chunk(s.last_good, report.advanced_steps);
}

void Wedges::on_model_chunk(Episode& ep, std::vector<float>& actions, SteadyClock::time_point observed,
                            const policy::Observation* reference, const std::vector<float>& normalized_state) {
  map_output(actions);
  std::lock_guard lock(ep.mu);
  EpisodeState& s = ep.state;
  // A late answer must not replace a newer chunk (requests of one episode can overlap under a deadline).
  if (!s.last_good.empty() && s.last_good.time > observed) return;
  s.last_good = {actions, int64_t(actions.size()) / dim_, dim_, observed};
  s.similar_skips = 0;
  if (reference) {
    s.has_reference = true;
    s.reference_state = normalized_state;
    s.reference_images = reference->images;
    s.reference_instruction = reference->instruction;
  }
}

void Wedges::map_output(std::vector<float>& actions) const {
  if (dim_ != model_dim_) {
    const int64_t rows = int64_t(actions.size()) / model_dim_;
    for (int64_t r = 1; r < rows; ++r)  // row 0 stays where it is; later rows move towards the front
      for (int64_t j = 0; j < dim_; ++j) actions[std::size_t(r * dim_ + j)] = actions[std::size_t(r * model_dim_ + j)];
    actions.resize(std::size_t(rows * dim_));
  }
  if (map_to_range_) opts_.embodiment->map_normalized_to_range(actions.data(), int64_t(actions.size()) / dim_);
}

void Wedges::unmap_output(std::vector<float>& actions) const {
  if (map_to_range_) opts_.embodiment->map_range_to_normalized(actions.data(), int64_t(actions.size()) / dim_);
}

void Wedges::on_fallback_chunk(Episode& ep, const std::vector<float>& actions, int64_t rows,
                               SteadyClock::time_point observed) {
  std::lock_guard lock(ep.mu);
  EpisodeState& s = ep.state;
  if (!s.last_good.empty() && s.last_good.time > observed) return;
  s.last_good = {actions, rows, dim_, observed};
  s.similar_skips = 0;
  s.has_reference = false;  // its observation was not kept: the next request runs the model
}

std::optional<std::vector<float>> Wedges::last_good(Episode& ep, WedgeReport& report) {
  std::lock_guard lock(ep.mu);
  const TimedChunk& c = ep.state.last_good;
  if (c.empty()) return std::nullopt;
  report.source = ActionSource::last_good;
  report.advanced_steps = elapsed_steps(c.time, SteadyClock::now(), rate_hz_);
  return advance_chunk(c, report.advanced_steps);
}

void Wedges::guard(Episode& ep, std::vector<float>& actions, int64_t rows, const std::vector<float>& state,
                   const std::string& request_id, const std::string& episode_id, WedgeReport& report) {
  if (!guard_) return;
  std::lock_guard lock(ep.mu);
  EpisodeState& s = ep.state;
  const auto now = SteadyClock::now();
  // The robot's current command is estimated as the last sent chunk's row at the control steps elapsed since.
  const float *previous = nullptr, *before_previous = nullptr;
  if (!s.last_sent.empty()) {
    const int64_t k = std::min(elapsed_steps(s.last_sent.time, now, rate_hz_), s.last_sent.rows - 1);
    previous = &s.last_sent.actions[std::size_t(k * dim_)];
    if (k >= 1) before_previous = &s.last_sent.actions[std::size_t((k - 1) * dim_)];
  }
  const float* fallback = int64_t(state.size()) == dim_ ? state.data() : nullptr;
  report.guard = guard_->apply(actions.data(), rows, dim_, previous, before_previous, fallback);
  s.last_sent = {actions, rows, dim_, now};
  if (!report.guard.violations.empty()) audit_->append(request_id, episode_id, report.guard.violations, model_embodiment_);
}

Json Wedges::response_fields(const WedgeReport& r) const {
  Json out = Json::object();
  out["action_source"] = action_source_name(r.source);
  if (guard_) {
    Json v = Json::array();
    for (const auto& x : r.guard.violations)
      v.push_back({{"step", x.step}, {"joint", x.joint}, {"limit", x.limit}, {"value", x.requested},
                   {"applied", x.applied}});
    out["guard_clamped"] = r.guard.clamped;
    out["guard_violations"] = std::move(v);
  }
  if (opts_.deadline_ms > 0) out["deadline_exceeded"] = r.deadline_exceeded;
  if (opts_.sampler.adaptive_threshold > 0) out["denoise_steps_used"] = r.denoise_steps_used;
  if (skip_enabled()) {
    out["action_skipped"] = r.skipped;
    out["similar_skips"] = r.similar_skips;
    out["similarity_distance"] = r.similarity_distance >= 0 && std::isfinite(r.similarity_distance)
                                     ? Json(r.similarity_distance) : Json(nullptr);
  }
  if (!opts_.cloud_fallback.empty()) {
    out["fallback_used"] = r.fallback_used;
    if (!r.fallback_error.empty()) out["fallback_error"] = r.fallback_error;
  }
  if (breaker_.enabled()) out["circuit_state"] = circuit_state_name(breaker_.state());
  if (opts_.inject_latency_ms > 0) out["injected_latency_ms"] = opts_.inject_latency_ms;
  if (!opts_.inject_failure_file.empty()) out["inject_failure_file"] = opts_.inject_failure_file;
  if (opts_.sampler.rtc) out["rtc_applied"] = r.rtc_applied;
  if (r.source == ActionSource::cache || r.source == ActionSource::last_good) out["advanced_steps"] = r.advanced_steps;
  if (!r.inference_error.empty()) out["inference_error"] = r.inference_error;
  if (!joints_.empty() && opts_.embodiment) out["joint_names"] = joints_;
  return out;
}

Json Wedges::config_json() const {
  Json w = Json::object();
  w["order"] = {"circuit_breaker", "similarity_skip", "inference", "cloud_fallback", "last_good_chunk",
                "embodiment_map", "action_guard", "trace_record"};
  w["control_rate_hz"] = rate_hz_;
  if (opts_.embodiment) {
    const auto& e = *opts_.embodiment;
    w["embodiment"] = {{"name", e.name}, {"joints", e.joints}, {"units", e.units},
                       {"control_rate_hz", e.control_rate_hz}, {"maps_normalized_output", map_to_range_},
                       {"model_action_dim", model_dim_}};
  }
  if (guard_) w["audit_log"] = opts_.audit_log;
  w["deadline_ms"] = opts_.deadline_ms > 0 ? Json(opts_.deadline_ms) : Json(nullptr);
  w["adaptive_threshold"] = opts_.sampler.adaptive_threshold > 0 ? Json(opts_.sampler.adaptive_threshold) : Json(nullptr);
  w["similarity"] = skip_enabled() ? Json{{"threshold", opts_.similarity_threshold}, {"max_skips", opts_.max_similar_skips}}
                                   : Json(nullptr);
  w["circuit_breaker"] = breaker_.enabled() ? Json{{"max_consecutive_crashes", opts_.max_consecutive_crashes},
                                                   {"reset_ms", opts_.circuit_reset_ms}}
                                            : Json(nullptr);
  w["cloud_fallback"] = opts_.cloud_fallback.empty() ? Json(nullptr)
                                                     : Json{{"url", opts_.cloud_fallback},
                                                            {"timeout_ms", opts_.fallback_timeout_ms}};
  w["inject_latency_ms"] = opts_.inject_latency_ms;
  w["inject_failure_file"] = opts_.inject_failure_file.empty() ? Json(nullptr) : Json(opts_.inject_failure_file);
  w["rtc"] = opts_.sampler.rtc ? Json{{"execution_horizon", opts_.sampler.rtc_execution_horizon},
                              {"max_guidance_weight", opts_.sampler.rtc_max_guidance_weight}}
                       : Json(nullptr);
  w["record"] = opts_.record ? Json(opts_.record->dir) : Json(nullptr);
  return w;
}

}  // namespace tether::runtime
