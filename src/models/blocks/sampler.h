// The flow-matching sampler as a block shared by the families: Euler over a time schedule in either direction (noise
// at t=1 to actions at t=0 as lerobot's SmolVLA and pi0 do, or 0 to 1 as GR00T does), with per-item adaptive step
// counts and real-time-chunking (RTC) guidance towards a previous chunk's leftover. Its arithmetic runs on the backend;
// the serving wedges only set its options.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "backend/backend.h"

namespace tether::models {

// lerobot's RTCAttentionSchedule: how the guidance weight falls off over the chunk.
enum class RtcSchedule { zeros, ones, linear, exp };
const char* rtc_schedule_name(RtcSchedule s);
// "zeros", "ones", "linear", "exp" (case-insensitive); anything else is invalid_argument naming `field`.
RtcSchedule parse_rtc_schedule(const std::string& name, const std::string& field = "rtc schedule");

// Per-position guidance weights [total] as lerobot's RTCProcessor.get_prefix_weights builds them: `start` is the
// inference delay (positions already committed, weight 1), `end` the execution horizon (weight 0 from there on; the
// caller caps it to the leftover length as upstream does), the schedule decides the ramp in between.
std::vector<float> rtc_prefix_weights(int start, int end, int total, RtcSchedule schedule);

// lerobot's guidance weight at tau = 1 - time: min(max_w, (1-tau)/tau * ((1-tau)^2 + tau^2) / (1-tau)^2), in float32,
// with +inf -> max_w and NaN -> 0 as torch.nan_to_num does.
float rtc_guidance_weight(float tau, float max_guidance_weight);

// How one batch item is denoised. Per item, so an item's result never depends on what it was batched with.
struct DenoiseControl {
  // > 0: stop once ||v_k - v_{k-1}|| / ||v_{k-1}|| < threshold (checked from the second step on), finishing with one
  // Euler jump over the remaining time. 0: every step.
  float adaptive_threshold = 0;
  // RTC guidance (empty target: off). Target: the previous chunk's leftover actions in the model's normalised space,
  // zero-padded to [chunk, width]; weights [chunk] from rtc_prefix_weights().
  std::vector<float> rtc_target, rtc_weights;
  float rtc_max_guidance_weight = 10;
  // RTC by inpainting (GR00T N1.7's own; empty prefix: off): x starts from these [rows, width] leftover rows instead
  // of noise, and each row's velocity is scaled by velocity_scale [chunk] (0 keeps a row as it started).
  std::vector<float> inpaint_prefix, velocity_scale;
};

// How a family's sampler follows the previous chunk (ModelSpec::rtc): lerobot's RTCProcessor guidance, or the
// inpainting GR00T N1.7 does natively.
enum class RtcMethod { guidance, inpainting };

// GR00T N1.7's real-time chunking as lerobot's rollout engine drives it (`GrootPolicy._prepare_n1_7_rtc_inputs`,
// `GR00TN17ActionHead.get_action_with_features`): the leftover's first min(n, execution_horizon) rows (normalised,
// [n, action_dim]), trailing all-zero rows dropped, are x's first rows (padding dims 0); the first
// min(inference_delay, rows) of them stay fixed (scale 0), the rest ramp in with r = 1 - exp(-rate * s) over
// s = linspace(0, 1, m + 2), r / r[-1], r[1..m], in float32; later rows scale 1. An all-zero leftover leaves the
// control off.
void inpainting_rtc(const std::vector<float>& leftover, int64_t action_dim, int64_t width, int64_t chunk,
                    int execution_horizon, int inference_delay, float ramp_rate, DenoiseControl& control);

// What a deployment chooses for the sampler (flags; the serve wedges only set these): adaptive stopping and RTC
// guidance. Per request they become a DenoiseControl.
struct SamplerOptions {
  float adaptive_threshold = 0;  // > 0: adaptive steps (see DenoiseControl)
  bool rtc = false;              // requests may carry RTC inputs (the previous chunk's leftover)
  int rtc_execution_horizon = 10;
  float rtc_max_guidance_weight = 10;
  RtcSchedule rtc_schedule = RtcSchedule::linear;
};

struct SampleShape {
  int64_t batch = 0, chunk = 0, width = 0;  // x and v are [batch, chunk, width]
  int64_t action_dim = 0;  // the first action_dim of each width values are real actions; the rest is padding
};

// Euler from `start` (where x is noise) to `end` in `steps` equal steps of dt = (end - start) / steps.
struct Schedule {
  double start = 1.0, end = 0.0;
  int64_t steps = 10;
  // false: time k is start + k * dt in float64, rounded to float32 (lerobot's loop). true: the time is a float32 that
  // starts at start and gets float32(dt) added after each step (FluxVLA's `time += dt` on a float32 tensor), which
  // drifts from the former by a few float32 steps.
  bool float32_time = false;
};

// velocity(x, time, v): the model's velocity for the whole batch at `time`, written to v (same layout as x).
using VelocityFn = std::function<void(backend::Ptr<const float> x, float time, backend::Ptr<float> v)>;

// Euler in place on the backend's x: x += dt * v at times start + k * dt, times and dt rounded from float64 as
// lerobot does (or accumulated in float32: Schedule::float32_time). `v` is the caller's [batch, chunk, width] buffer the velocity is written to. With default controls the
// arithmetic is exactly that loop and nothing is allocated per step. RTC guidance needs the noise-at-1 direction.
// `on_step0_velocity`, when set, sees the model's first velocity (before any guidance).
// Returns the velocity evaluations each item used (schedule.steps unless it stopped early).
std::vector<int> euler_sample(backend::Backend& be, backend::Ptr<float> x, backend::Ptr<float> v,
                              const SampleShape& shape, const Schedule& schedule,
                              const std::vector<DenoiseControl>& controls, const VelocityFn& velocity,
                              const std::function<void(backend::Ptr<const float> v)>& on_step0_velocity = {});

}  // namespace tether::models
