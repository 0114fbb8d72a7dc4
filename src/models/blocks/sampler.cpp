// The Euler flow-matching sampler with adaptive step counts and RTC guidance (see sampler.h).
#include "models/blocks/sampler.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <limits>
#include <numbers>

#include "core/error.h"

namespace tether::models {

namespace {

// torch.nan_to_num with nan=0, posinf given, neginf the lowest finite float.
float nan_to_num(float x, float posinf) {
  if (std::isnan(x)) return 0.0f;
  if (std::isinf(x)) return x > 0 ? posinf : std::numeric_limits<float>::lowest();
  return x;
}

// torch.linspace(1, 0, n + 2)[1:-1] for the ramp between start and end, computed the way torch's CPU kernel does
// (float32 step; the second half counted back from the end).
std::vector<float> ramp(int start, int end, int total) {
  const int n = total - std::max(total - end, 0) - start;
  if (end <= start || n <= 0) return {};
  const int64_t steps = n + 2, halfway = steps / 2;
  const float step = (0.0f - 1.0f) / float(steps - 1);
  std::vector<float> w;
  for (int64_t i = 1; i + 1 < steps; ++i)
    w.push_back(i < halfway ? 1.0f + step * float(i) : 0.0f - step * float(steps - i - 1));
  return w;
}

void check_control(const DenoiseControl& c, int64_t item, const SampleShape& s) {
  const std::string where = "denoise control of item " + std::to_string(item) + ": ";
  if (!std::isfinite(c.adaptive_threshold) || c.adaptive_threshold < 0)
    throw Error(ErrorCode::invalid_argument, where + "adaptive_threshold must be finite and >= 0");
  if (!c.inpaint_prefix.empty()) {
    if (int64_t(c.inpaint_prefix.size()) % s.width != 0 || int64_t(c.inpaint_prefix.size()) > s.chunk * s.width)
      throw Error(ErrorCode::invalid_argument, where + "inpaint_prefix has " + std::to_string(c.inpaint_prefix.size()) +
                                                   " values, expected whole rows of " + std::to_string(s.width) +
                                                   ", at most " + std::to_string(s.chunk));
    if (int64_t(c.velocity_scale.size()) != s.chunk)
      throw Error(ErrorCode::invalid_argument, where + "velocity_scale has " + std::to_string(c.velocity_scale.size()) +
                                                   " values, expected " + std::to_string(s.chunk));
    if (!c.rtc_target.empty())
      throw Error(ErrorCode::invalid_argument, where + "RTC guidance and inpainting are exclusive");
  }
  if (c.rtc_target.empty()) return;
  if (int64_t(c.rtc_target.size()) != s.chunk * s.width)
    throw Error(ErrorCode::invalid_argument, where + "rtc_target has " + std::to_string(c.rtc_target.size()) +
                                                 " values, expected " + std::to_string(s.chunk) + "x" +
                                                 std::to_string(s.width));
  if (int64_t(c.rtc_weights.size()) != s.chunk)
    throw Error(ErrorCode::invalid_argument, where + "rtc_weights has " + std::to_string(c.rtc_weights.size()) +
                                                 " values, expected " + std::to_string(s.chunk));
  if (!std::isfinite(c.rtc_max_guidance_weight) || c.rtc_max_guidance_weight <= 0)
    throw Error(ErrorCode::invalid_argument, where + "rtc_max_guidance_weight must be finite and > 0");
}

// RTC guidance corrects the velocity by err^T d(x1)/d(x_t) with x1 = x_t - time * v, i.e. err - time * err^T dv/dx_t.
// There is no backward pass here, so the Jacobian is taken as the identity (correction = err, the time * dv/dx_t term
// is dropped). lerobot 0.6.1's RTCProcessor evaluates v before it enables gradients on x_t, so its autograd product
// reduces to the same identity. The backend's rtc_guide applies it with lerobot's float32 arithmetic.

}  // namespace

const char* rtc_schedule_name(RtcSchedule s) {
  switch (s) {
    case RtcSchedule::zeros: return "zeros";
    case RtcSchedule::ones: return "ones";
    case RtcSchedule::linear: return "linear";
    case RtcSchedule::exp: return "exp";
  }
  return "?";
}

RtcSchedule parse_rtc_schedule(const std::string& name, const std::string& field) {
  std::string lower = name;
  std::transform(lower.begin(), lower.end(), lower.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
  for (RtcSchedule s : {RtcSchedule::zeros, RtcSchedule::ones, RtcSchedule::linear, RtcSchedule::exp})
    if (lower == rtc_schedule_name(s)) return s;
  throw Error(ErrorCode::invalid_argument, field + ": '" + name + "' is not one of zeros, ones, linear, exp");
}

std::vector<float> rtc_prefix_weights(int start, int end, int total, RtcSchedule schedule) {
  if (total < 1 || start < 0 || end < 0)
    throw Error(ErrorCode::invalid_argument, "rtc_prefix_weights: needs total >= 1, start >= 0, end >= 0 (got " +
                                                 std::to_string(start) + ", " + std::to_string(end) + ", " +
                                                 std::to_string(total) + ")");
  start = std::min(start, end);
  std::vector<float> w;
  switch (schedule) {
    case RtcSchedule::zeros:
      w.assign(std::size_t(total), 0.0f);
      std::fill_n(w.begin(), std::min(start, total), 1.0f);
      return w;
    case RtcSchedule::ones:
      w.assign(std::size_t(total), 1.0f);
      if (end < total) std::fill(w.begin() + end, w.end(), 0.0f);
      return w;
    case RtcSchedule::linear:
    case RtcSchedule::exp: break;
  }
  std::vector<float> r = ramp(start, end, total);
  if (schedule == RtcSchedule::exp) {
    const float denom = float(std::numbers::e - 1.0);
    for (float& x : r) x = x * (std::expm1(x) / denom);
  }
  w.assign(std::size_t(std::min(start, total)), 1.0f);
  w.insert(w.end(), r.begin(), r.end());
  w.resize(w.size() + std::size_t(std::max(total - end, 0)), 0.0f);
  return w;
}

float rtc_guidance_weight(float tau, float max_guidance_weight) {
  const float one_minus = 1.0f - tau;
  const float squared = one_minus * one_minus;
  const float inv_r2 = (squared + tau * tau) / squared;
  const float c = nan_to_num(one_minus / tau, max_guidance_weight);
  return std::min(nan_to_num(c * inv_r2, max_guidance_weight), max_guidance_weight);
}

void inpainting_rtc(const std::vector<float>& leftover, int64_t action_dim, int64_t width, int64_t chunk,
                    int execution_horizon, int inference_delay, float ramp_rate, DenoiseControl& c) {
  int64_t rows = std::min<int64_t>(int64_t(leftover.size()) / action_dim, std::max(execution_horizon, 0));
  rows = std::min(rows, chunk);
  // The engine pads a short leftover with zero rows and upstream drops trailing all-zero rows, so a real row that
  // is exactly zero at the end goes as well.
  while (rows > 0) {
    float sum = 0;
    for (int64_t j = 0; j < action_dim; ++j) sum += std::fabs(leftover[std::size_t((rows - 1) * action_dim + j)]);
    if (sum > 0) break;
    --rows;
  }
  c.inpaint_prefix.clear();
  c.velocity_scale.clear();
  if (rows == 0) return;
  c.inpaint_prefix.assign(std::size_t(rows * width), 0.0f);
  for (int64_t r = 0; r < rows; ++r)
    std::copy_n(&leftover[std::size_t(r * action_dim)], action_dim, &c.inpaint_prefix[std::size_t(r * width)]);
  const int64_t frozen = std::clamp<int64_t>(inference_delay, 0, rows), ramped = rows - frozen;
  c.velocity_scale.assign(std::size_t(chunk), 1.0f);
  for (int64_t r = 0; r < frozen; ++r) c.velocity_scale[std::size_t(r)] = 0.0f;
  // torch.linspace(0, 1, m) in float32: start + step * i for the first half, end - step * (m - 1 - i) for the rest.
  const int64_t m = ramped + 2;
  const float step = 1.0f / float(m - 1);
  std::vector<float> ramp(static_cast<std::size_t>(m));
  for (int64_t i = 0; i < m; ++i) {
    const float s = i < m / 2 ? step * float(i) : 1.0f - step * float(m - 1 - i);
    ramp[std::size_t(i)] = 1.0f - std::exp(-ramp_rate * s);
  }
  const float last = std::max(ramp.back(), 1e-8f);
  for (int64_t r = 0; r < ramped; ++r) c.velocity_scale[std::size_t(frozen + r)] = ramp[std::size_t(r + 1)] / last;
}

std::vector<int> euler_sample(backend::Backend& be, backend::Ptr<float> x, backend::Ptr<float> v,
                              const SampleShape& s, const Schedule& schedule,
                              const std::vector<DenoiseControl>& controls, const VelocityFn& velocity,
                              const std::function<void(backend::Ptr<const float> v)>& on_step0_velocity) {
  const int64_t B = s.batch, n = s.chunk * s.width, num_steps = schedule.steps;
  if (num_steps < 1) throw Error(ErrorCode::invalid_argument, "euler_sample: num_steps must be >= 1");
  if (!std::isfinite(schedule.start) || !std::isfinite(schedule.end) || schedule.start == schedule.end)
    throw Error(ErrorCode::invalid_argument, "euler_sample: the schedule needs two different finite end points");
  if (int64_t(controls.size()) != B)
    throw Error(ErrorCode::invalid_argument, "euler_sample: " + std::to_string(controls.size()) +
                                                 " denoise controls for a batch of " + std::to_string(B));
  bool adaptive = false, rtc = false;
  for (int64_t b = 0; b < B; ++b) {
    check_control(controls[b], b, s);
    adaptive = adaptive || controls[b].adaptive_threshold > 0;
    rtc = rtc || !controls[b].rtc_target.empty();
  }
  if (rtc && !(schedule.start == 1.0 && schedule.end == 0.0))
    throw Error(ErrorCode::unsupported, "euler_sample: RTC guidance is defined for schedules from noise at 1 to 0");
  // Everything the loop needs is sized and uploaded here: the steps themselves never allocate.
  backend::Array<float> prev_v = adaptive ? be.alloc<float>(B * n) : backend::Array<float>();
  backend::Array<float> targets = rtc ? be.alloc<float>(B * n) : backend::Array<float>();
  backend::Array<float> weights = rtc ? be.alloc<float>(B * s.chunk) : backend::Array<float>();
  for (int64_t b = 0; b < B && rtc; ++b) {
    if (controls[b].rtc_target.empty()) continue;
    be.upload(controls[b].rtc_target.data(), n, targets.at(b * n));
    be.upload(controls[b].rtc_weights.data(), s.chunk, weights.at(b * s.chunk));
  }
  // Inpainting RTC: the leftover rows replace the noise they start from.
  for (int64_t b = 0; b < B; ++b)
    if (!controls[b].inpaint_prefix.empty())
      be.upload(controls[b].inpaint_prefix.data(), int64_t(controls[b].inpaint_prefix.size()), x + b * n);
  std::vector<int> steps(std::size_t(B), 0);
  std::vector<uint8_t> done(std::size_t(B), 0);
  int64_t active = B;
  const double dt = (schedule.end - schedule.start) / double(num_steps);
  const float dt32 = float(dt);
  float time32 = float(schedule.start);
  for (int64_t step = 0; step < num_steps && active > 0; ++step, time32 += dt32) {
    const double time = schedule.float32_time ? double(time32) : schedule.start + double(step) * dt;
    velocity(x, float(time), v);
    if (step == 0 && on_step0_velocity) on_step0_velocity(v);
    for (int64_t b = 0; b < B; ++b) {
      if (done[b]) continue;  // frozen: its velocity is computed with the batch but never used
      const DenoiseControl& c = controls[b];
      const backend::Ptr<float> xb = x + b * n, vb = v + b * n;
      ++steps[b];
      // Upstream steps x + (dt * v) * scale; v * scale first is the same bits whenever dt is a power of two (the
      // released 4 steps), and at most an ulp apart otherwise.
      for (std::size_t r = 0; r < c.velocity_scale.size(); ++r)
        if (c.velocity_scale[r] != 1.0f) be.scale(vb + int64_t(r) * s.width, s.width, c.velocity_scale[r]);
      if (!c.rtc_target.empty())
        be.rtc_guide(xb, vb, targets.at(b * n), weights.at(b * s.chunk), s.chunk, s.width, float(time),
                     rtc_guidance_weight(float(1.0 - time), c.rtc_max_guidance_weight));
      if (c.adaptive_threshold > 0) {
        const backend::Ptr<float> pb = prev_v.at(b * n);
        // On the last step a jump is the ordinary step, so the check starts at the second and ends before the last.
        if (step > 0 && step + 1 < num_steps) {
          // ||v - prev|| < threshold * ||prev|| over the real action dims (padding dims never reach the output).
          const auto [diff, norm] = be.change_norms(vb, pb, s.chunk, s.width, s.action_dim);
          if (std::sqrt(diff) < double(c.adaptive_threshold) * std::sqrt(norm)) {
            // The velocity stopped changing: integrate it as a constant over the remaining time, straight to the end.
            be.axpy(xb, vb, n, float(schedule.end - time));
            done[b] = 1;
            --active;
            continue;
          }
        }
        be.copy_rows(vb, 0, pb, 0, 1, n);
      }
      be.axpy(xb, vb, n, dt32);
    }
  }
  return steps;
}

}  // namespace tether::models
