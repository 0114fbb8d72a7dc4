// Per-episode state of the action server: the last good chunk (what a deadline miss or a similarity skip answers
// with), the last chunk sent (the guard's history), the similarity-skip counter and the observation the cached chunk
// was computed from. Requests name their episode with `episode_id`; a new id starts from nothing.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "policy/policy.h"

namespace tether::runtime {

using SteadyClock = std::chrono::steady_clock;

// An action chunk [rows, dim] in robot units and when it became valid (its row 0 is the command for that moment).
struct TimedChunk {
  std::vector<float> actions;
  int64_t rows = 0, dim = 0;
  SteadyClock::time_point time{};
  bool empty() const { return rows == 0; }
};

// Control steps elapsed since `since` at `control_rate_hz` (0 when the rate is unknown).
int64_t elapsed_steps(SteadyClock::time_point since, SteadyClock::time_point now, double control_rate_hz);

// The chunk as seen `steps` control steps later: the first `steps` rows are dropped (already executed) and the last
// row is held to keep the length, so a robot that plays it from its start stays on the original trajectory.
std::vector<float> advance_chunk(const TimedChunk& chunk, int64_t steps);

struct EpisodeState {
  TimedChunk last_good;  // raw model (or fallback) output in robot units, before the guard
  TimedChunk last_sent;  // what the robot was last told, after the guard
  int similar_skips = 0;  // consecutive requests answered from last_good
  // The observation last_good was computed from (for the similarity test).
  bool has_reference = false;
  std::vector<float> reference_state;  // normalised
  std::map<std::string, vision::Image> reference_images;
  std::string reference_instruction;
};

struct Episode {
  std::mutex mu;
  EpisodeState state;
  SteadyClock::time_point last_used{};
};

// A bounded map of episodes: the least recently used one is forgotten beyond `max_episodes`.
class EpisodeStore {
 public:
  explicit EpisodeStore(std::size_t max_episodes = 1024) : max_(max_episodes) {}
  // Requests without an id share the episode "" (one robot per server).
  std::shared_ptr<Episode> get(const std::string& id);
  // Forgets episode `id`: its next request starts from nothing (no last good chunk, guard history or skip cache).
  // A request still holding it finishes against the old state, which does not carry over. False when it had none.
  bool end(const std::string& id);
  std::size_t size() const;

 private:
  std::size_t max_;
  mutable std::mutex mu_;
  std::map<std::string, std::shared_ptr<Episode>> episodes_;
};

// How far a new observation is from a reference one, in [0, inf): the larger of
//  - the largest change of any state value after the policy's input normalisation (mean/std units for MEAN_STD), and
//  - for each camera, the mean absolute pixel difference divided by 255 (0: identical frames, 1: black vs white).
// Infinite when the instruction, the camera set or an image size differs.
double observation_distance(const policy::Observation& obs, const std::vector<float>& normalized_state,
                            const EpisodeState& reference);

}  // namespace tether::runtime
