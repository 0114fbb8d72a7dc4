// Joint-limit clamping of action chunks and the append-only audit log of what was clamped.
#include "runtime/action_guard.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <optional>

#include "core/json_util.h"

namespace tether::runtime {

namespace {

// Bounds are computed in double from float commands and the clamped value is stored as float again, so a value may
// sit a rounding error past the bound it was clamped to; such values pass.
double slack(double bound) { return 1e-6 * std::max(1.0, std::abs(bound)); }

std::optional<double> finite_at(const float* values, size_t j) {
  if (!values || !std::isfinite(values[j])) return std::nullopt;
  return double(values[j]);
}

void check_limits(const std::string& joint, const policy::JointLimits& l, double rate_hz) {
  auto bad = [&](const std::string& what) {
    throw Error(ErrorCode::invalid_argument, "action guard: joint '" + joint + "': " + what);
  };
  if (l.has_position_limits && !(l.min_position <= l.max_position)) bad("min_position is greater than max_position");
  if (l.has_velocity_limits && !(l.max_velocity > 0)) bad("max_velocity must be positive");
  if (l.has_acceleration_limits && !(l.max_acceleration > 0)) bad("max_acceleration must be positive");
  if ((l.has_velocity_limits || l.has_acceleration_limits) && !(rate_hz > 0 && std::isfinite(rate_hz)))
    bad("rate limits need a positive control rate, got " + std::to_string(rate_hz) + " Hz");
}

std::string utc_now_iso8601() {
  const auto now = std::chrono::system_clock::now();
  const std::time_t secs = std::chrono::system_clock::to_time_t(now);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm tm{};
  gmtime_r(&secs, &tm);
  char buf[40];
  const size_t n = std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%S", &tm);
  std::snprintf(buf + n, sizeof buf - n, ".%03dZ", int(ms));
  return buf;
}

}  // namespace

ActionGuard::ActionGuard(std::vector<std::string> joints, std::vector<policy::JointLimits> limits,
                         double control_rate_hz)
    : joints_(std::move(joints)), limits_(std::move(limits)), rate_hz_(control_rate_hz) {
  if (joints_.size() != limits_.size())
    throw Error(ErrorCode::invalid_argument, "action guard: " + std::to_string(joints_.size()) + " joints but " +
                                                 std::to_string(limits_.size()) + " sets of limits");
  for (size_t j = 0; j < joints_.size(); ++j) check_limits(joints_[j], limits_[j], rate_hz_);
}

GuardReport ActionGuard::apply(float* actions, int64_t rows, int64_t dim, const float* previous,
                               const float* before_previous, const float* fallback) const {
  if (dim != int64_t(joints_.size()))
    throw Error(ErrorCode::invalid_argument, "action guard: the chunk has " + std::to_string(dim) +
                                                 " values per row, the guard has " +
                                                 std::to_string(joints_.size()) + " joints");
  GuardReport report;
  const double dt = rate_hz_ > 0 ? 1.0 / rate_hz_ : 0;
  for (int64_t r = 0; r < rows; ++r) {
    float* row = actions + r * dim;
    // The two commands before this row: earlier rows (already clamped), else the caller's history.
    const float* p1 = r >= 1 ? row - dim : previous;
    const float* p2 = r >= 2 ? row - 2 * dim : r == 1 ? previous : before_previous;
    for (size_t j = 0; j < size_t(dim); ++j) {
      const policy::JointLimits& l = limits_[j];
      const std::optional<double> h1 = finite_at(p1, j), h2 = h1 ? finite_at(p2, j) : std::nullopt;
      double x = row[j];
      bool changed = false;
      auto record = [&](const char* limit, double applied) {
        report.violations.push_back({r, joints_[j], limit, x, double(float(applied))});
        x = applied;
        changed = true;
      };
      auto bound = [&](double lo, double hi, const char* below, const char* above) {
        if (x < lo - slack(lo)) record(below, lo);
        else if (x > hi + slack(hi)) record(above, hi);
      };
      if (!std::isfinite(x)) {
        const double midpoint = l.has_position_limits ? 0.5 * (l.min_position + l.max_position) : 0.0;
        record("non_finite", h1 ? *h1 : finite_at(fallback, j).value_or(midpoint));
      }
      if (l.has_acceleration_limits && h2) {
        const double step = l.max_acceleration * dt * dt, centre = *h1 + (*h1 - *h2);
        bound(centre - step, centre + step, "acceleration", "acceleration");
      }
      if (l.has_velocity_limits && h1) {
        const double step = l.max_velocity * dt;
        bound(*h1 - step, *h1 + step, "velocity", "velocity");
      }
      if (l.has_position_limits) bound(l.min_position, l.max_position, "position_min", "position_max");
      if (changed) row[j] = float(x);
    }
  }
  report.clamped = !report.violations.empty();
  return report;
}

AuditLog::AuditLog(std::string path) : path_(std::move(path)) {
  fd_ = ::open(path_.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  if (fd_ < 0)
    throw Error(ErrorCode::io, path_ + ": cannot open the audit log for appending: " + std::strerror(errno));
}

AuditLog::~AuditLog() {
  if (fd_ >= 0) ::close(fd_);
}

void AuditLog::append(const std::string& request_id, const std::string& episode_id,
                      const std::vector<GuardViolation>& violations, const std::string& embodiment) {
  if (violations.empty()) return;
  const std::string time = utc_now_iso8601();
  std::string lines;
  for (const auto& v : violations) {
    Json line = {{"time", time},     {"request_id", request_id}, {"episode_id", episode_id},
                 {"step", v.step},   {"joint", v.joint},         {"limit", v.limit},
                 {"requested", v.requested}, {"applied", v.applied}};
    if (!embodiment.empty()) line["embodiment"] = embodiment;
    // Ids come from clients: invalid UTF-8 is replaced rather than thrown on.
    lines += line.dump(-1, ' ', false, Json::error_handler_t::replace);
    lines += '\n';
  }
  std::lock_guard lock(mu_);
  std::string out;
  if (torn_) {
    out.reserve(lines.size() + 1);
    out += '\n';
    out += lines;
  }
  const std::string& batch = torn_ ? out : lines;
  ssize_t n;
  do n = ::write(fd_, batch.data(), batch.size());
  while (n < 0 && errno == EINTR);
  if (n == ssize_t(batch.size())) {
    torn_ = false;
    return;
  }
  if (n > 0) torn_ = true;
  write_errors_.fetch_add(1);
}

}  // namespace tether::runtime
