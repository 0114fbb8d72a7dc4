// The safety wedges between a request and the robot, in their fixed order:
//   1. circuit breaker   refuse (503) or hand to the fallback while local inference is known broken
//   2. similarity skip   reuse the episode's cached chunk when the observation barely changed
//   3. inference         under --deadline-ms, with --inject-latency-ms, adaptive steps and RTC inside the model;
//                        a chunk with NaN/Inf counts as a failed inference (breaker, fallback) and is never cached
//   4. cloud fallback    when inference failed, missed its deadline or the circuit is open
//   5. last good chunk   on a deadline miss the fallback could not cover
//   6. embodiment map    a padded action output cut to the embodiment's joints; normalised model output -> the
//                        embodiment's action range (checkpoints without action stats)
//   7. action guard      NaN/Inf, acceleration, velocity, position limits: always last, whatever produced the chunk
//   8. trace record      one hash-chained JSON line per request
// This class holds the synchronous parts and the per-episode state; the server drives the asynchronous ones
// (waiting for the model under a deadline, calling the fallback).
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/json_util.h"
#include "policy/embodiment.h"
#include "runtime/action_guard.h"
#include "runtime/circuit_breaker.h"
#include "runtime/episodes.h"
#include "runtime/trace_recorder.h"

namespace tether::runtime {

struct WedgeOptions {
  std::optional<policy::Embodiment> embodiment;  // --embodiment / --custom-embodiment-config
  std::optional<policy::SafetyConfig> safety;    // --safety-config: overrides the embodiment's limits per joint
  std::string audit_log;                         // where guard clamps are appended (the guard is on: required)
  double control_rate_hz = 0;  // 0: the safety config's, else the embodiment's, else kDefaultControlRateHz

  double deadline_ms = 0;  // 0: off
  double similarity_threshold = 0;  // with max_similar_skips > 0
  int max_similar_skips = 0;
  int max_consecutive_crashes = 0;  // 0: no circuit breaker
  int circuit_reset_ms = 60000;
  std::string cloud_fallback;  // URL of another Tether server (its /act is called)
  int fallback_timeout_ms = 2000;
  std::string fallback_api_key;
  double inject_latency_ms = 0;
  std::string inject_failure_file;  // while this file exists every forward pass throws (rehearsing failures)

  models::SamplerOptions sampler;  // adaptive steps and RTC: the sampler block's own options, passed through

  std::optional<TraceOptions> record;  // --record DIR
  bool record_images_full = false;

  std::size_t max_episodes = 1024;
};

// Control rate used to turn elapsed time into executed steps when nothing configures one (lerobot records at 30 fps).
inline constexpr double kDefaultControlRateHz = 30.0;

// How many of the model's action values the embodiment keeps: all of them when its joint count equals the model's
// action_dim; its first J when the model's action is the padded vector of a base checkpoint (action_dim ==
// max_action_dim, more values than the robot has joints), as openpi's robot output transforms keep actions[:, :J].
// Throws invalid_argument naming both counts otherwise.
int64_t embodiment_action_dim(const policy::Embodiment& embodiment, const models::ModelSpec& spec);

// Where a response's actions came from.
enum class ActionSource { model, cache, last_good, fallback };
const char* action_source_name(ActionSource s);

// What the wedges did for one request; rendered into the /act response, the trace line and /metrics.
struct WedgeReport {
  ActionSource source = ActionSource::model;
  bool skipped = false;         // similarity skip
  int similar_skips = 0;        // consecutive skips including this one
  double similarity_distance = -1;
  bool deadline_exceeded = false;
  int64_t advanced_steps = 0;   // a cached chunk was advanced by this many control steps
  int denoise_steps_used = 0;
  bool fallback_used = false;
  std::string fallback_error;   // why the fallback did not answer, when it was tried and failed
  std::string inference_error;  // why local inference failed, when it did
  bool rtc_applied = false;
  GuardReport guard;
};

class Wedges {
 public:
  explicit Wedges(WedgeOptions options);

  // Checks the options against the loaded model (the embodiment's joints against action_dim, see
  // embodiment_action_dim) and builds the guard. Throws tether::Error naming the mismatch.
  void bind_model(const models::ModelSpec& spec, bool actions_normalized);

  const WedgeOptions& options() const { return opts_; }
  double control_rate_hz() const { return rate_hz_; }
  bool guard_enabled() const { return guard_.has_value(); }
  bool skip_enabled() const { return opts_.similarity_threshold > 0 && opts_.max_similar_skips > 0; }
  const std::vector<std::string>& joint_names() const { return joints_; }
  // Values per action row after the embodiment map (what /act answers and the fallback must answer with); the
  // model's action_dim unless the embodiment cuts a padded output.
  int64_t action_dim() const { return dim_; }
  CircuitBreaker& breaker() { return breaker_; }
  const CircuitBreaker& breaker() const { return breaker_; }
  EpisodeStore& episodes() { return episodes_; }
  const EpisodeStore& episodes() const { return episodes_; }
  TraceRecorder* recorder() { return recorder_.get(); }

  // 2. The cached chunk, advanced to now, when `obs` is within the similarity threshold of the observation the
  // cached chunk was computed from and fewer than K skips happened in a row; fills `report`.
  std::optional<std::vector<float>> try_skip(Episode& ep, const policy::Observation& obs,
                                             const std::vector<float>& normalized_state, WedgeReport& report);
  // 3. Success of local inference (called on the inference thread, even after the request's deadline passed):
  // maps the chunk to the embodiment's range in place and makes it the episode's last good chunk.
  void on_model_chunk(Episode& ep, std::vector<float>& actions, SteadyClock::time_point observed,
                      const policy::Observation* reference, const std::vector<float>& normalized_state);
  // 6. A padded model output cut to the embodiment's joints, then normalised output -> the embodiment's action range
  // when the checkpoint lacks action stats. `actions` holds rows x the model's action_dim values, rows x
  // action_dim() after.
  void map_output(std::vector<float>& actions) const;
  // The inverse of the range map for actions a client sends back (RTC's leftover), in place; identity when the
  // output is not mapped.
  void unmap_output(std::vector<float>& actions) const;
  // 4. A chunk from the fallback server becomes the last good one too.
  void on_fallback_chunk(Episode& ep, const std::vector<float>& actions, int64_t rows, SteadyClock::time_point observed);
  // 5. The last good chunk advanced to now, if the episode has one.
  std::optional<std::vector<float>> last_good(Episode& ep, WedgeReport& report);
  // 7. Guard (when configured) against the episode's last sent chunk; records the chunk as sent and appends clamps
  // to the audit log. `state`: the request's state, the stand-in command for a NaN when nothing was sent yet.
  void guard(Episode& ep, std::vector<float>& actions, int64_t rows, const std::vector<float>& state,
             const std::string& request_id, const std::string& episode_id, WedgeReport& report);

  // The wedges' part of an /act response (only the fields of enabled wedges) and of /config.
  Json response_fields(const WedgeReport& report) const;
  Json config_json() const;

 private:
  WedgeOptions opts_;
  double rate_hz_ = kDefaultControlRateHz;
  int64_t rows_ = 0, dim_ = 0, model_dim_ = 0;  // dim_: after the embodiment map; model_dim_: what the model outputs
  bool map_to_range_ = false;
  std::vector<std::string> joints_;
  std::string model_embodiment_;  // the bound model's embodiment tag, named in audit lines
  std::optional<ActionGuard> guard_;
  std::unique_ptr<AuditLog> audit_;
  CircuitBreaker breaker_;
  EpisodeStore episodes_;
  std::unique_ptr<TraceRecorder> recorder_;
};

}  // namespace tether::runtime
