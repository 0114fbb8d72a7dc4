// The normalisation arithmetic, operation for operation as lerobot writes it.
#include "policy/normalizer.h"

#include <algorithm>
#include <array>
#include <cmath>

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
  const auto mask_it = f.stats.find("mean_std_mask");  // GR00T N1.6's columns decoded with mean/std instead
  const std::vector<float>* mean_std = mask_it == f.stats.end() ? nullptr : &mask_it->second;
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
        if (mean_std && (*mean_std)[j] != 0.f) {
          // Isaac-GR00T's unnormalize_values_meanstd: x * std + mean, unclipped; x itself where std is 0.
          const float mean = stat("mean")[j], sd = stat("std")[j];
          if (sd != 0.f) v = inverse ? v * sd + mean : (v - mean) / sd;
          break;
        }
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

namespace {

// lerobot's rot6d_to_matrix and xyz_rot6d_to_homogeneous (groot/utils.py), float64: the 6 values are the first two
// rows of the rotation, Gram-Schmidt orthonormalised, the third row their cross product.
using Pose = std::array<std::array<double, 4>, 4>;

double norm3(const double* v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

Pose xyz_rot6d_pose(const float* p) {
  double r1[3], r2[3];
  for (int k = 0; k < 3; ++k) r1[k] = p[3 + k], r2[k] = p[6 + k];
  const double n1 = norm3(r1);
  for (double& v : r1) v /= n1;
  const double d = r1[0] * r2[0] + r1[1] * r2[1] + r1[2] * r2[2];
  for (int k = 0; k < 3; ++k) r2[k] -= d * r1[k];
  const double n2 = norm3(r2);
  for (double& v : r2) v /= n2;
  const double r3[3] = {r1[1] * r2[2] - r1[2] * r2[1], r1[2] * r2[0] - r1[0] * r2[2], r1[0] * r2[1] - r1[1] * r2[0]};
  Pose t{};
  for (int k = 0; k < 3; ++k) t[0][k] = r1[k], t[1][k] = r2[k], t[2][k] = r3[k], t[k][3] = p[k];
  t[3][3] = 1.0;
  return t;
}

// Group g's slice of the raw state, once the group is known to lie inside both the action row and the state.
const float* group_state(const models::RelativeAction& g, int64_t dim, const std::vector<float>& raw_state) {
  if (g.action_offset + g.dim > dim || g.state_offset + g.dim > int64_t(raw_state.size()))
    throw Error(ErrorCode::internal, "relative action group '" + g.name + "' lies outside the action or state");
  return raw_state.data() + g.state_offset;
}

// A joint group's columns of every row moved by sign * state (+1: to absolute, -1: back to relative; exact).
void shift_joints(const models::RelativeAction& g, float* actions, int64_t rows, int64_t dim, const float* ref,
                  float sign) {
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t c = 0; c < g.dim; ++c) actions[r * dim + g.action_offset + c] += sign * ref[c];
}

}  // namespace

void Normalizer::to_absolute(float* actions, int64_t rows, int64_t dim, const std::vector<float>& raw_state) const {
  for (const models::RelativeAction& g : relative_) {
    const float* ref = group_state(g, dim, raw_state);
    if (g.kind == models::RelativeAction::Kind::joint) {
      shift_joints(g, actions, rows, dim, ref, 1.0f);
      continue;
    }
    const Pose t_ref = xyz_rot6d_pose(ref);
    for (int64_t r = 0; r < rows; ++r) {
      float* a = actions + r * dim + g.action_offset;
      const Pose t_rel = xyz_rot6d_pose(a);
      Pose t{};
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j)
          for (int k = 0; k < 4; ++k) t[i][j] += t_ref[i][k] * t_rel[k][j];
      // Back to xyz + the first two rows, cast to float32.
      for (int k = 0; k < 3; ++k) a[k] = float(t[k][3]), a[3 + k] = float(t[0][k]), a[6 + k] = float(t[1][k]);
    }
  }
}

void Normalizer::to_relative(float* actions, int64_t rows, int64_t dim, const std::vector<float>& raw_state) const {
  for (const models::RelativeAction& g : relative_) {
    if (g.kind != models::RelativeAction::Kind::joint)
      throw Error(ErrorCode::internal, "relative action group '" + g.name + "' is a pose: no leftover re-anchoring");
    shift_joints(g, actions, rows, dim, group_state(g, dim, raw_state), -1.0f);
  }
}

std::vector<std::string> Normalizer::describe() const {
  std::vector<std::string> out;
  for (const auto& [key, f] : features_)
    out.push_back(key + ": " + norm_mode_name(f.mode) +
                  (f.mode == NormMode::identity ? "" : f.has_stats ? " (stats present)" : " (no stats: identity)"));
  for (const auto& [key, f] : features_)
    if (const auto m = f.stats.find("mean_std_mask"); m != f.stats.end())
      out.push_back(key + ": the groups in mean_std_embedding_keys decoded with mean/std, unclipped (" +
                    std::to_string(std::count(m->second.begin(), m->second.end(), 1.f)) + " of " +
                    std::to_string(m->second.size()) + " values)");
  for (const auto& g : relative_)
    out.push_back("action '" + g.name + "': relative to the state (" +
                  (g.kind == models::RelativeAction::Kind::joint ? "added to it" : "an xyz+rot6d pose composed with it") +
                  ")");
  return out;
}

}  // namespace tether::policy
