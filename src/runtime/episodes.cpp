// Episode bookkeeping and the observation distance used by the similarity skip.
#include "runtime/episodes.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace tether::runtime {

int64_t elapsed_steps(SteadyClock::time_point since, SteadyClock::time_point now, double control_rate_hz) {
  if (control_rate_hz <= 0 || now <= since) return 0;
  return int64_t(std::chrono::duration<double>(now - since).count() * control_rate_hz);
}

std::vector<float> advance_chunk(const TimedChunk& chunk, int64_t steps) {
  std::vector<float> out(chunk.actions.size());
  for (int64_t r = 0; r < chunk.rows; ++r) {
    const int64_t src = std::min(r + std::max<int64_t>(steps, 0), chunk.rows - 1);
    std::copy_n(chunk.actions.begin() + src * chunk.dim, chunk.dim, out.begin() + r * chunk.dim);
  }
  return out;
}

std::shared_ptr<Episode> EpisodeStore::get(const std::string& id) {
  std::lock_guard lock(mu_);
  auto& slot = episodes_[id];
  if (!slot) {
    slot = std::make_shared<Episode>();
    if (episodes_.size() > max_) {
      // Forget the least recently used other episode; a request still holding it keeps its copy alive.
      auto oldest = episodes_.end();
      for (auto it = episodes_.begin(); it != episodes_.end(); ++it)
        if (it->first != id && (oldest == episodes_.end() || it->second->last_used < oldest->second->last_used))
          oldest = it;
      if (oldest != episodes_.end()) episodes_.erase(oldest);
    }
  }
  slot->last_used = SteadyClock::now();
  return slot;
}

bool EpisodeStore::end(const std::string& id) {
  std::lock_guard lock(mu_);
  return episodes_.erase(id) > 0;
}

std::size_t EpisodeStore::size() const {
  std::lock_guard lock(mu_);
  return episodes_.size();
}

double observation_distance(const policy::Observation& obs, const std::vector<float>& normalized_state,
                            const EpisodeState& ref) {
  constexpr double inf = std::numeric_limits<double>::infinity();
  if (!ref.has_reference || obs.instruction != ref.reference_instruction ||
      normalized_state.size() != ref.reference_state.size() || obs.images.size() != ref.reference_images.size())
    return inf;
  double d = 0;
  for (std::size_t i = 0; i < normalized_state.size(); ++i)
    d = std::max(d, std::fabs(double(normalized_state[i]) - double(ref.reference_state[i])));
  for (const auto& [camera, img] : obs.images) {
    const auto it = ref.reference_images.find(camera);
    if (it == ref.reference_images.end() || it->second.width != img.width || it->second.height != img.height ||
        it->second.rgb.size() != img.rgb.size())
      return inf;
    uint64_t sum = 0;
    for (std::size_t i = 0; i < img.rgb.size(); ++i)
      sum += uint64_t(std::abs(int(img.rgb[i]) - int(it->second.rgb[i])));
    if (!img.rgb.empty()) d = std::max(d, double(sum) / (255.0 * double(img.rgb.size())));
  }
  return std::isnan(d) ? inf : d;
}

}  // namespace tether::runtime
