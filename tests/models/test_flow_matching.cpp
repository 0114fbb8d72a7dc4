// The shared Euler sampler on synthetic velocity fields: the default path is the plain loop bit for bit, adaptive
// stopping (jump, per-item step counts, batch independence), RTC guidance arithmetic and lerobot's prefix weights, and
// GR00T's inpainting RTC.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <vector>

#include "core/error.h"
#include "models/blocks/sampler.h"

using namespace tether;
using namespace tether::models;

namespace {

using backend::Ptr;
// Fields are written on host arrays; the CPU backend's addresses are host addresses.
using HostField = std::function<void(const float* x, float t, float* v)>;
VelocityFn as_velocity(HostField f) {
  return [f](Ptr<const float> x, float t, Ptr<float> v) { f(x.address(), t, v.address()); };
}
backend::Backend& cpu_backend() {
  static const auto be = backend::make_backend("cpu");
  return *be;
}

constexpr int64_t kChunk = 4, kWidth = 3, kActionDim = 2, kSize = kChunk * kWidth;

std::vector<float> start_noise(int64_t batch) {
  std::vector<float> x(std::size_t(batch * kSize));
  for (std::size_t i = 0; i < x.size(); ++i) x[i] = std::sin(1.7f * float(i) + 0.3f);
  return x;
}

// A field that depends on x and time; `wobble` per item sets how much it still changes late in the trajectory.
HostField field(std::vector<float> wobble) {
  return [wobble](const float* x, float t, float* v) {
    for (std::size_t b = 0; b < wobble.size(); ++b)
      for (int64_t i = 0; i < kSize; ++i) {
        const int64_t k = int64_t(b) * kSize + i;
        v[k] = 0.05f * x[k] + 1.0f + wobble[b] * t * t * t * std::cos(float(i));
      }
  };
}

// The loop euler_sample replaced, verbatim in arithmetic.
std::vector<float> plain_euler(std::vector<float> x, int64_t steps, const HostField& velocity) {
  std::vector<float> v(x.size());
  const double dt = -1.0 / double(steps);
  const float dt32 = float(dt);
  for (int64_t step = 0; step < steps; ++step) {
    velocity(x.data(), float(1.0 + double(step) * dt), v.data());
    for (std::size_t i = 0; i < x.size(); ++i) x[i] += dt32 * v[i];
  }
  return x;
}

std::vector<int> sample(std::vector<float>& x, int64_t steps, const std::vector<DenoiseControl>& controls,
                        const HostField& velocity) {
  const int64_t batch = int64_t(controls.size());
  std::vector<float> v(x.size());
  return euler_sample(cpu_backend(), Ptr<float>(x.data()), Ptr<float>(v.data()), {batch, kChunk, kWidth, kActionDim},
                      Schedule{1.0, 0.0, steps}, controls, as_velocity(velocity));
}

void expect_weights(const std::vector<float>& got, const std::vector<float>& want) {
  ASSERT_EQ(got.size(), want.size());
  for (std::size_t i = 0; i < want.size(); ++i) EXPECT_NEAR(got[i], want[i], 1e-6) << "position " << i;
}

}  // namespace

TEST(EulerSample, DefaultControlsAreThePlainLoopBitForBit) {
  const auto velocity = field({0.3f, 2.0f});
  std::vector<float> x = start_noise(2);
  const std::vector<float> want = plain_euler(x, 10, velocity);
  const std::vector<int> steps = sample(x, 10, {DenoiseControl{}, DenoiseControl{}}, velocity);
  EXPECT_EQ(x, want);
  EXPECT_EQ(steps, std::vector<int>({10, 10}));
}

TEST(EulerSample, StepZeroHookSeesTheFirstVelocity) {
  std::vector<float> x = start_noise(1), v(x.size()), seen;
  const std::vector<float> x0 = x;
  euler_sample(cpu_backend(), Ptr<float>(x.data()), Ptr<float>(v.data()), {1, kChunk, kWidth, kActionDim}, Schedule{1.0, 0.0, 3},
               {DenoiseControl{}}, as_velocity(field({1.0f})),
               [&](Ptr<const float> vel) { seen.assign(vel.address(), vel.address() + kSize); });
  std::vector<float> want(x0.size());
  field({1.0f})(x0.data(), 1.0f, want.data());
  EXPECT_EQ(seen, want);
}

TEST(EulerSample, HugeThresholdStopsAtStepTwoWithAJumpToZero) {
  const auto velocity = field({1.0f});
  DenoiseControl c;
  c.adaptive_threshold = 1e9f;
  std::vector<float> x = start_noise(1);
  // By hand: one Euler step from t=1, then the second velocity (t=0.9) integrated over the remaining 0.9.
  std::vector<float> want = x, v0(x.size()), v1(x.size());
  const double dt = -1.0 / 10.0;
  velocity(want.data(), 1.0f, v0.data());
  for (int64_t i = 0; i < kSize; ++i) want[i] += float(dt) * v0[i];
  velocity(want.data(), float(1.0 + dt), v1.data());
  for (int64_t i = 0; i < kSize; ++i) want[i] += float(0.0 - (1.0 + dt)) * v1[i];

  const std::vector<int> steps = sample(x, 10, {c}, velocity);
  EXPECT_EQ(steps, std::vector<int>({2}));
  EXPECT_EQ(x, want);
}

TEST(EulerSample, ThresholdZeroRunsEveryStep) {
  const auto velocity = field({1.0f});
  std::vector<float> x = start_noise(1);
  const std::vector<float> want = plain_euler(x, 7, velocity);
  EXPECT_EQ(sample(x, 7, {DenoiseControl{}}, velocity), std::vector<int>({7}));
  EXPECT_EQ(x, want);
}

TEST(EulerSample, ItemsStopAtTheirOwnStepAndIgnoreTheirNeighbours) {
  // Item 0's field barely changes (stops early); item 1's keeps changing (runs longer).
  DenoiseControl c;
  c.adaptive_threshold = 0.05f;
  std::vector<float> both = start_noise(2);
  const std::vector<int> steps = sample(both, 10, {c, c}, field({0.01f, 1.0f}));
  std::printf("[ steps      ] threshold 0.05: item 0 stopped after %d steps, item 1 after %d\n", steps[0], steps[1]);
  EXPECT_LT(steps[0], steps[1]);
  EXPECT_LT(steps[1], 10) << "the slowly settling item should still stop before the end";

  for (int item = 0; item < 2; ++item) {
    const std::vector<float> start = start_noise(2);  // the same start noise the item had in the batch
    std::vector<float> alone(start.begin() + item * kSize, start.begin() + (item + 1) * kSize);
    const std::vector<int> s = sample(alone, 10, {c}, field({item == 0 ? 0.01f : 1.0f}));
    EXPECT_EQ(s[0], steps[item]);
    EXPECT_EQ(alone, std::vector<float>(both.begin() + item * kSize, both.begin() + (item + 1) * kSize))
        << "item " << item << " depends on its batch neighbour";
  }
}

TEST(EulerSample, AdaptiveEndsCloseToTheFullRunWhenTheFieldSettles) {
  const auto velocity = field({0.3f});
  DenoiseControl c;
  c.adaptive_threshold = 0.05f;
  std::vector<float> x = start_noise(1);
  const std::vector<float> full = plain_euler(x, 10, velocity);
  const int steps = sample(x, 10, {c}, velocity)[0];
  double diff = 0;
  for (int64_t i = 0; i < kSize; ++i) diff = std::max(diff, std::fabs(double(x[i]) - double(full[i])));
  std::printf("[ adaptive   ] %d of 10 steps, max |diff| vs all steps %.3e\n", steps, diff);
  EXPECT_LT(steps, 10);
  EXPECT_GT(diff, 0.0);
  EXPECT_LT(diff, 0.5);
}

TEST(EulerSample, RtcWithZeroWeightsIsNoGuidanceBitForBit) {
  const auto velocity = field({1.0f});
  DenoiseControl c;
  c.rtc_target.assign(kSize, 2.5f);
  c.rtc_weights.assign(kChunk, 0.0f);
  std::vector<float> x = start_noise(1);
  const std::vector<float> want = plain_euler(x, 10, velocity);
  sample(x, 10, {c}, velocity);
  EXPECT_EQ(x, want);
}

TEST(EulerSample, RtcGuidanceFollowsLerobotsFormula) {
  // Two steps by hand: v' = v - w_guid(tau) * (target - (x - t * v)) * weight[row].
  const auto velocity = field({1.0f});
  DenoiseControl c;
  for (int64_t i = 0; i < kSize; ++i) c.rtc_target.push_back(0.1f * float(i));
  c.rtc_weights = {1.0f, 0.5f, 0.25f, 0.0f};
  c.rtc_max_guidance_weight = 4.0f;
  std::vector<float> x = start_noise(1), want = x, v(kSize);
  for (int step = 0; step < 2; ++step) {
    const double t = 1.0 - 0.5 * step;
    velocity(want.data(), float(t), v.data());
    const float g = rtc_guidance_weight(float(1.0 - t), 4.0f);
    for (int64_t i = 0; i < kSize; ++i) {
      const float x1 = want[i] - float(t) * v[i];
      v[i] = v[i] - g * ((c.rtc_target[i] - x1) * c.rtc_weights[i / kWidth]);
      want[i] += float(-0.5) * v[i];
    }
  }
  sample(x, 2, {c}, velocity);
  EXPECT_EQ(x, want);
}

TEST(EulerSample, RejectsMismatchedControls) {
  std::vector<float> x = start_noise(2), v(x.size());
  EXPECT_THROW(euler_sample(cpu_backend(), Ptr<float>(x.data()), Ptr<float>(v.data()), {2, kChunk, kWidth, kActionDim},
                            Schedule{1.0, 0.0, 4}, {DenoiseControl{}}, as_velocity(field({1.0f, 1.0f}))),
               Error);  // one control for two items
  DenoiseControl c;
  c.rtc_target.assign(kSize - 1, 0.0f);
  c.rtc_weights.assign(kChunk, 1.0f);
  EXPECT_THROW(sample(x, 4, {c, DenoiseControl{}}, field({1.0f, 1.0f})), Error);
  DenoiseControl bad;
  bad.adaptive_threshold = -1.0f;
  EXPECT_THROW(sample(x, 4, {bad, DenoiseControl{}}, field({1.0f, 1.0f})), Error);
}

TEST(RtcGuidanceWeight, MatchesTheClosedFormWithLerobotsInfAndNanHandling) {
  EXPECT_EQ(rtc_guidance_weight(0.0f, 10.0f), 10.0f);  // (1-tau)/tau = +inf -> max
  EXPECT_FLOAT_EQ(rtc_guidance_weight(0.5f, 10.0f), 2.0f);
  EXPECT_NEAR(rtc_guidance_weight(0.1f, 10.0f), 9.0 * (0.81 + 0.01) / 0.81, 1e-5);
  EXPECT_NEAR(rtc_guidance_weight(0.9f, 10.0f), (0.1 / 0.9) * (0.01 + 0.81) / 0.01, 1e-4);
  EXPECT_EQ(rtc_guidance_weight(0.95f, 10.0f), 10.0f);  // 19.05 capped
  EXPECT_EQ(rtc_guidance_weight(1.0f, 10.0f), 0.0f);    // 0 * inf = NaN -> 0
  EXPECT_EQ(rtc_guidance_weight(0.9f, 5.0f), 5.0f);
}

TEST(RtcPrefixWeights, LinearRampsFromTheDelayToTheHorizon) {
  expect_weights(rtc_prefix_weights(2, 6, 10, RtcSchedule::linear), {1, 1, 0.8f, 0.6f, 0.4f, 0.2f, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(0, 5, 10, RtcSchedule::linear),
                 {5 / 6.f, 4 / 6.f, 3 / 6.f, 2 / 6.f, 1 / 6.f, 0, 0, 0, 0, 0});
  // Delay past the horizon: the delay is cut to the horizon, nothing ramps.
  expect_weights(rtc_prefix_weights(7, 4, 10, RtcSchedule::linear), {1, 1, 1, 1, 0, 0, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(3, 3, 6, RtcSchedule::linear), {1, 1, 1, 0, 0, 0});
  // Horizon past the chunk: the ramp runs to the end of the chunk.
  expect_weights(rtc_prefix_weights(2, 15, 10, RtcSchedule::linear),
                 {1, 1, 8 / 9.f, 7 / 9.f, 6 / 9.f, 5 / 9.f, 4 / 9.f, 3 / 9.f, 2 / 9.f, 1 / 9.f});
}

TEST(RtcPrefixWeights, ExpBendsTheLinearRamp) {
  auto bend = [](double l) { return float(l * std::expm1(l) / (std::exp(1.0) - 1.0)); };
  expect_weights(rtc_prefix_weights(2, 6, 10, RtcSchedule::exp),
                 {1, 1, bend(0.8), bend(0.6), bend(0.4), bend(0.2), 0, 0, 0, 0});
  EXPECT_NEAR(bend(0.8), 0.570589, 1e-6);  // lerobot 0.6.1 prints 0.570589005947113
  expect_weights(rtc_prefix_weights(7, 4, 10, RtcSchedule::exp), {1, 1, 1, 1, 0, 0, 0, 0, 0, 0});
  std::vector<float> want = {1, 1};
  for (int k = 8; k >= 1; --k) want.push_back(bend(k / 9.0));
  expect_weights(rtc_prefix_weights(2, 15, 10, RtcSchedule::exp), want);
}

TEST(RtcPrefixWeights, ZerosAndOnes) {
  expect_weights(rtc_prefix_weights(2, 6, 10, RtcSchedule::zeros), {1, 1, 0, 0, 0, 0, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(7, 4, 10, RtcSchedule::zeros), {1, 1, 1, 1, 0, 0, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(2, 15, 10, RtcSchedule::zeros), {1, 1, 0, 0, 0, 0, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(0, 6, 4, RtcSchedule::zeros), {0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(2, 6, 10, RtcSchedule::ones), {1, 1, 1, 1, 1, 1, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(7, 4, 10, RtcSchedule::ones), {1, 1, 1, 1, 0, 0, 0, 0, 0, 0});
  expect_weights(rtc_prefix_weights(2, 15, 10, RtcSchedule::ones), {1, 1, 1, 1, 1, 1, 1, 1, 1, 1});
}

TEST(RtcPrefixWeights, ScheduleNamesRoundTrip) {
  for (RtcSchedule s : {RtcSchedule::zeros, RtcSchedule::ones, RtcSchedule::linear, RtcSchedule::exp})
    EXPECT_EQ(parse_rtc_schedule(rtc_schedule_name(s)), s);
  EXPECT_EQ(parse_rtc_schedule("LINEAR"), RtcSchedule::linear);
  EXPECT_THROW(parse_rtc_schedule("cosine"), Error);
  EXPECT_THROW(rtc_prefix_weights(-1, 4, 10, RtcSchedule::linear), Error);
}

TEST(EulerSample, RunsFromZeroToOneAsGr00tDoes) {
  // GR00T's schedule: noise at t=0, dt = +1/steps, times 0, 1/4, 2/4, 3/4.
  const auto velocity = field({0.7f});
  std::vector<float> x = start_noise(1), want = x, v(x.size());
  for (int64_t step = 0; step < 4; ++step) {
    velocity(want.data(), float(0.0 + double(step) * 0.25), v.data());
    for (int64_t i = 0; i < kSize; ++i) want[i] += float(0.25) * v[i];
  }
  std::vector<float> vb(x.size());
  euler_sample(cpu_backend(), Ptr<float>(x.data()), Ptr<float>(vb.data()), {1, kChunk, kWidth, kActionDim},
               Schedule{0.0, 1.0, 4}, {DenoiseControl{}}, as_velocity(velocity));
  EXPECT_EQ(x, want);
  // RTC's guidance weight is defined on the noise-at-1 direction only.
  DenoiseControl c;
  c.rtc_target.assign(kSize, 0.0f);
  c.rtc_weights.assign(kChunk, 1.0f);
  EXPECT_THROW(euler_sample(cpu_backend(), Ptr<float>(x.data()), Ptr<float>(vb.data()), {1, kChunk, kWidth, kActionDim},
                            Schedule{0.0, 1.0, 4}, {c}, as_velocity(velocity)),
               Error);
}

// GR00T's inpainting RTC: which leftover rows are kept, the per-row scale, and the sampler keeping frozen rows fixed.
TEST(InpaintingRtc, KeepsTheFirstHorizonRowsDropsTrailingZeroRowsAndClampsTheDelay) {
  // 3 leftover rows of 2 action values; row 2 is all zero.
  const std::vector<float> leftover = {0.5f, -0.5f, 0.25f, 0.0f, 0.0f, 0.0f};
  DenoiseControl c;
  inpainting_rtc(leftover, kActionDim, kWidth, kChunk, /*horizon=*/8, /*delay=*/5, 6.0f, c);
  // The trailing zero row is dropped: 2 rows, both frozen (the delay is clamped to them), padding dims 0.
  EXPECT_EQ(c.inpaint_prefix, (std::vector<float>{0.5f, -0.5f, 0.0f, 0.25f, 0.0f, 0.0f}));
  EXPECT_EQ(c.velocity_scale, (std::vector<float>{0.0f, 0.0f, 1.0f, 1.0f}));
  // The horizon cuts the leftover first; no delay: the kept rows ramp in towards 1.
  inpainting_rtc(leftover, kActionDim, kWidth, kChunk, /*horizon=*/1, /*delay=*/0, 6.0f, c);
  ASSERT_EQ(c.inpaint_prefix.size(), std::size_t(kWidth));
  const float r1 = 1.0f - std::exp(-6.0f * 0.5f), r2 = 1.0f - std::exp(-6.0f);
  EXPECT_NEAR(c.velocity_scale[0], r1 / r2, 1e-7);
  EXPECT_EQ(c.velocity_scale[1], 1.0f);
  // A leftover of zeros leaves RTC off.
  inpainting_rtc(std::vector<float>(4, 0.0f), kActionDim, kWidth, kChunk, 4, 1, 6.0f, c);
  EXPECT_TRUE(c.inpaint_prefix.empty());
  EXPECT_TRUE(c.velocity_scale.empty());
}

TEST(InpaintingRtc, FrozenRowsStayOnTheLeftoverAndOthersFollowTheField) {
  const auto velocity = field({1.0f});
  const std::vector<float> leftover = {0.5f, -0.5f, 0.25f, 0.75f};
  DenoiseControl c;
  inpainting_rtc(leftover, kActionDim, kWidth, kChunk, 2, 1, 6.0f, c);
  std::vector<float> x = start_noise(1);
  const std::vector<float> noise = x;
  sample(x, 4, {c}, velocity);
  // Row 0 frozen: exactly the leftover (its padding value 0 too); row 1 started from the leftover and moved;
  // rows 2-3 went on from the noise as plain Euler would move them.
  EXPECT_EQ(std::vector<float>(x.begin(), x.begin() + kWidth), (std::vector<float>{0.5f, -0.5f, 0.0f}));
  EXPECT_NE(x[kWidth], 0.25f);
  // The field is element-wise, so rows 2-3 equal plain Euler from the same noise, bit for bit.
  const std::vector<float> plain = plain_euler(noise, 4, velocity);
  EXPECT_EQ(std::vector<float>(x.begin() + 2 * kWidth, x.end()), std::vector<float>(plain.begin() + 2 * kWidth, plain.end()));
  // Guidance and inpainting together are refused.
  c.rtc_target.assign(std::size_t(kSize), 0.0f);
  c.rtc_weights.assign(std::size_t(kChunk), 1.0f);
  std::vector<float> y = start_noise(1);
  EXPECT_THROW(sample(y, 4, {c}, velocity), Error);
}
