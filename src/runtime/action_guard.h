// The action guard: clamps an action chunk to per-joint limits before it reaches the robot, and the audit log that
// records every clamp as a JSON line.
#pragma once

#include <atomic>
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

#include "policy/embodiment.h"

namespace tether::runtime {

struct GuardViolation {
  int64_t step;       // row of the chunk
  std::string joint;
  std::string limit;  // "non_finite", "acceleration", "velocity", "position_min", "position_max"
  double requested;   // the value as it reached this check (NaN/Inf for non_finite)
  double applied;     // the value this check left
};

struct GuardReport {
  bool clamped = false;
  std::vector<GuardViolation> violations;
};

// Checks, per row and per joint, in this order (each clamp records one violation; the value a check leaves is what
// the next check sees, and a row's final values are what the next row is checked against):
//   1. non_finite    NaN/Inf -> the last safe command: the previous row, else `previous`, else `fallback`, else the
//                    midpoint of the joint's position limits, or 0 without position limits.
//   2. acceleration  |v_i - v_{i-1}| <= max_acceleration * dt with v_i = (a_i - a_{i-1}) / dt; needs two earlier
//                    commands (for row 0 `previous` and `before_previous`, for row 1 `previous`).
//   3. velocity      |a_i - a_{i-1}| <= max_velocity * dt; needs one earlier command (for row 0 `previous`).
//   4. position      min_position <= a_i <= max_position. Last, so it wins over the rate limits: a command is never
//                    sent outside the joint's range, even if reaching the range needs a faster move.
// dt = 1 / control_rate_hz. A value beyond a bound by no more than float rounding (1e-6 relative) passes, so guarding
// a guarded chunk again changes nothing. A chunk already inside every limit is left bit-for-bit unchanged.
class ActionGuard {
 public:
  // `limits[i]` belongs to `joints[i]`; control_rate_hz must be positive when any rate limit is on.
  ActionGuard(std::vector<std::string> joints, std::vector<policy::JointLimits> limits, double control_rate_hz);

  // Clamps a chunk [rows, dim] in place; dim must be the number of joints. `previous` / `before_previous`: the last
  // commands sent before this chunk, dim values each (null when unknown). `fallback`: dim values used to replace a
  // non-finite value when no earlier command exists (null: the position midpoint). Non-finite history is ignored.
  GuardReport apply(float* actions, int64_t rows, int64_t dim, const float* previous, const float* before_previous,
                    const float* fallback) const;

  const std::vector<std::string>& joints() const { return joints_; }
  const std::vector<policy::JointLimits>& limits() const { return limits_; }
  double control_rate_hz() const { return rate_hz_; }

 private:
  std::vector<std::string> joints_;
  std::vector<policy::JointLimits> limits_;
  double rate_hz_;
};

// Appends one JSON line per violation:
//   {"time":"2025-06-01T12:00:00.123Z","request_id":"...","episode_id":"...","step":3,"joint":"elbow",
//    "limit":"velocity","requested":1.25,"applied":1.1}
// ("requested" is null for a non-finite value). Each append is one write(2) on an O_APPEND descriptor under a
// mutex, so lines from concurrent requests (and other processes appending to the same file) never interleave.
// There is no fsync: a line is safe from a crash of the server once append returns, not from a power loss.
class AuditLog {
 public:
  // Opens (creating, mode 0644) for appending; failure throws tether::Error(io) naming the path.
  explicit AuditLog(std::string path);
  ~AuditLog();
  AuditLog(const AuditLog&) = delete;
  AuditLog& operator=(const AuditLog&) = delete;

  // Never throws on I/O errors: a failed or short write is counted in write_errors(), and the next append starts on
  // a fresh line so one torn line cannot corrupt the following ones.
  // `embodiment`: the GR00T embodiment tag of the model that answered (empty: none), so that one log shared by
  // several robots tells them apart.
  void append(const std::string& request_id, const std::string& episode_id,
              const std::vector<GuardViolation>& violations, const std::string& embodiment = "");
  int64_t write_errors() const { return write_errors_.load(); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
  int fd_ = -1;
  std::mutex mu_;
  bool torn_ = false;  // the last write was short: the file may end inside a line
  std::atomic<int64_t> write_errors_{0};
};

}  // namespace tether::runtime
