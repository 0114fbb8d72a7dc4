// The normalisation arithmetic, operation for operation as lerobot writes it.
#include "policy/normalizer.h"

#include "core/error.h"

namespace tether::policy {

using models::required_stats;

void Normalizer::apply(const std::string& key, float* x, int64_t n, Direction direction) const {
  auto it = features_.find(key);
  if (it == features_.end() || it->second.mode == NormMode::identity || !it->second.has_stats) return;
  const FeatureNorm& f = it->second;
  auto stat = [&](const char* name) -> const std::vector<float>& { return f.stats.at(name); };
  const std::size_t width = stat(required_stats(f.mode)[0].c_str()).size();
  if (width == 0 || n % int64_t(width) != 0)
    throw Error(ErrorCode::invalid_argument, key + ": " + std::to_string(n) + " values do not match the stats width " +
                                                 std::to_string(width));
  // Float32 arithmetic in the same operation order as upstream so results match to the last bit.
  const bool inverse = direction == Direction::unnormalize;
  for (int64_t i = 0; i < n; ++i) {
    const std::size_t j = std::size_t(i) % width;
    float& v = x[i];
    switch (f.mode) {
      case NormMode::mean_std: {
        const float mean = stat("mean")[j], std = stat("std")[j];
        if (direction == Direction::invert_unnormalize) v = std == 0.f ? 0.f : (v - mean) / std;
        else v = inverse ? v * std + mean : (v - mean) / (std + eps_);
        break;
      }
      case NormMode::min_max: {
        const float lo = stat("min")[j];
        float denom = stat("max")[j] - lo;
        if (denom == 0.f) denom = eps_;
        v = inverse ? (v + 1.f) / 2.f * denom + lo : 2.f * (v - lo) / denom - 1.f;
        break;
      }
      case NormMode::quantiles:
      case NormMode::quantile10: {
        const bool q1 = f.mode == NormMode::quantiles;
        const float lo = stat(q1 ? "q01" : "q10")[j];
        float denom = stat(q1 ? "q99" : "q90")[j] - lo;
        if (denom == 0.f) denom = eps_;
        v = inverse ? (v + 1.f) * denom / 2.f + lo : 2.f * (v - lo) / denom - 1.f;
        break;
      }
      case NormMode::min_max_clipped: {
        // GR00T N1.7's pack and decode steps (lerobot): float32, in their operation order.
        const float lo = stat("min")[j], d = stat("max")[j] - lo;
        if (inverse) {
          const float c = v < -1.f ? -1.f : v > 1.f ? 1.f : v;
          v = (c + 1.f) * 0.5f * d + lo;
        } else {
          // Clipped both ways: the pack step clips, and a decoded action came from a clipped value.
          v = d == 0.f ? 0.f : 2.f * (v - lo) / d - 1.f;
          v = v < -1.f ? -1.f : v > 1.f ? 1.f : v;
        }
        break;
      }
      case NormMode::identity: break;
    }
  }
}

std::vector<std::string> Normalizer::describe() const {
  std::vector<std::string> out;
  for (const auto& [key, f] : features_)
    out.push_back(key + ": " + norm_mode_name(f.mode) +
                  (f.mode == NormMode::identity ? "" : f.has_stats ? " (stats present)" : " (no stats: identity)"));
  return out;
}

}  // namespace tether::policy
