// Adaptive denoise steps and real-time chunking end to end on the demo policy: step counts, batch independence,
// RTC off when its weights are zero, the seam to the previous chunk shrinking under RTC, request validation.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <string>

#include "policy/policy.h"
#include "vision/image.h"

using namespace tether;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";

policy::Policy& demo() {
  static std::unique_ptr<policy::Policy> p = policy::Policy::load(kDemo);
  return *p;
}

policy::Observation observation(uint64_t seed) {
  policy::Observation o;
  o.images[demo().spec().cameras.at(0)] = vision::load_image(std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png");
  o.state = {0.1f, -0.2f, 0.3f, 0.0f, 0.5f, -0.4f};
  o.instruction = "pick up the red cube";
  o.seed = seed;
  return o;
}

policy::ActionChunk predict_one(const policy::Observation& o) { return demo().predict({o}).items.at(0); }

double max_abs_diff(const std::vector<float>& a, const std::vector<float>& b, int64_t n) {
  double m = 0;
  for (int64_t i = 0; i < n; ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
  return m;
}

// max |new[i] - leftover[i]| over the first `rows` actions: the jump the robot sees when it switches chunks.
double seam(const std::vector<float>& fresh, const std::vector<float>& leftover, int rows) {
  return max_abs_diff(fresh, leftover, int64_t(rows) * demo().spec().action_dim);
}

std::string error_of(const policy::Observation& o) {
  try {
    demo().predict({o});
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    return e.what();
  }
  return "";
}

}  // namespace

TEST(AdaptiveSteps, DefaultAndThresholdZeroRunEveryStep) {
  const policy::ActionChunk plain = predict_one(observation(3));
  EXPECT_EQ(plain.denoise_steps_used, demo().spec().num_steps);
  policy::Observation o = observation(3);
  o.adaptive_threshold = 0.0f;
  const policy::ActionChunk zero = predict_one(o);
  EXPECT_EQ(zero.denoise_steps_used, demo().spec().num_steps);
  EXPECT_EQ(zero.actions, plain.actions);
}

TEST(AdaptiveSteps, HugeThresholdStopsAfterTwoSteps) {
  policy::Observation o = observation(3);
  o.adaptive_threshold = 1e9f;
  const policy::ActionChunk fast = predict_one(o);
  EXPECT_EQ(fast.denoise_steps_used, 2);
  const policy::ActionChunk full = predict_one(observation(3));
  const double diff = max_abs_diff(fast.actions, full.actions, int64_t(full.actions.size()));
  std::printf("[ adaptive   ] 2 of %lld steps: max |diff| vs all steps %.4f (robot units)\n",
              static_cast<long long>(demo().spec().num_steps), diff);
  EXPECT_GT(diff, 0.0);
}

TEST(AdaptiveSteps, AnItemIgnoresANeighbourThatStopsAtAnotherStep) {
  // Same instruction, so both items have the same prefix length: the batched model itself is then bit-exact with
  // the single-item run, and any difference would come from the sampler.
  policy::Observation a = observation(21), b = observation(22);
  a.adaptive_threshold = 0.05f;
  b.adaptive_threshold = 1e9f;  // stops after two steps, while a goes on
  const policy::ActionChunk alone = predict_one(a);
  const policy::Prediction both = demo().predict({b, a});
  std::printf("[ adaptive   ] threshold 0.05: %d steps alone, %d in the batch; neighbour %d steps\n",
              alone.denoise_steps_used, both.items[1].denoise_steps_used, both.items[0].denoise_steps_used);
  EXPECT_NE(both.items[0].denoise_steps_used, alone.denoise_steps_used);
  EXPECT_EQ(both.items[1].denoise_steps_used, alone.denoise_steps_used);
  EXPECT_EQ(both.items[1].actions, alone.actions);
  EXPECT_EQ(both.items[0].actions, predict_one(b).actions);

  // With a neighbour of another instruction (another prefix length) the model's own batched arithmetic may differ
  // in the last bits, so compare against the same batch with the neighbour running every step instead.
  b.instruction = "open the drawer";
  policy::Observation b_full = b;
  b_full.adaptive_threshold = 0;
  const policy::Prediction early = demo().predict({b, a}), late = demo().predict({b_full, a});
  EXPECT_EQ(early.items[0].denoise_steps_used, 2);
  EXPECT_EQ(late.items[0].denoise_steps_used, demo().spec().num_steps);
  EXPECT_EQ(early.items[1].actions, late.items[1].actions);
  EXPECT_EQ(early.items[1].actions, alone.actions) << "a neighbour with another prompt length changed the result";
}

TEST(RealTimeChunking, ZeroWeightsAreNoGuidanceBitForBit) {
  const policy::ActionChunk prev = predict_one(observation(5));
  policy::Observation o = observation(6);
  // The zeros schedule with no delay weights every position 0.
  o.rtc = policy::Observation::Rtc{.prev_actions = prev.actions, .inference_delay = 0, .execution_horizon = 10,
                                   .max_guidance_weight = 10, .schedule = models::RtcSchedule::zeros};
  EXPECT_EQ(predict_one(o).actions, predict_one(observation(6)).actions);
}

TEST(RealTimeChunking, TheSeamToThePreviousChunkShrinks) {
  // The robot executed `executed` actions of the previous chunk; the rest is the leftover the new chunk should
  // continue. The new chunk comes from other noise, so without guidance it starts somewhere else.
  const int64_t A = demo().spec().action_dim;
  const int executed = 5;
  const policy::ActionChunk prev = predict_one(observation(11));
  const std::vector<float> leftover(prev.actions.begin() + executed * A, prev.actions.end());
  const std::vector<float> free = predict_one(observation(12)).actions;
  for (int delay : {1, 3, 5, 10}) {
    policy::Observation o = observation(12);
    o.rtc = policy::Observation::Rtc{.prev_actions = leftover, .inference_delay = delay};
    const std::vector<float> guided = predict_one(o).actions;
    const double without = seam(free, leftover, delay), with = seam(guided, leftover, delay);
    std::printf("[ rtc seam   ] delay %2d: max |new - leftover| over the first %d actions: without RTC %.4f, "
                "with RTC %.4f (robot units)\n",
                delay, delay, without, with);
    EXPECT_LT(with, 0.25 * without) << "delay " << delay;
  }
}

TEST(RealTimeChunking, ValidatesTheRequestFields) {
  const int64_t A = demo().spec().action_dim, C = demo().spec().chunk_size;
  auto with_rtc = [&](std::vector<float> prev, int delay, int horizon) {
    policy::Observation o = observation(1);
    o.rtc = policy::Observation::Rtc{.prev_actions = std::move(prev), .inference_delay = delay,
                                     .execution_horizon = horizon};
    return o;
  };
  const std::vector<float> ok(std::size_t(3 * A), 0.5f);
  EXPECT_NE(error_of(with_rtc({}, 0, 10)).find("rtc.prev_actions"), std::string::npos);
  EXPECT_NE(error_of(with_rtc(std::vector<float>(std::size_t(A + 1), 0.f), 0, 10)).find("rtc.prev_actions"),
            std::string::npos);
  EXPECT_NE(error_of(with_rtc(std::vector<float>(std::size_t((C + 1) * A), 0.f), 0, 10)).find("rtc.prev_actions"),
            std::string::npos);
  EXPECT_NE(error_of(with_rtc(ok, -1, 10)).find("rtc.inference_delay"), std::string::npos);
  EXPECT_NE(error_of(with_rtc(ok, int(C), 10)).find("rtc.inference_delay"), std::string::npos);
  EXPECT_NE(error_of(with_rtc(ok, 0, 0)).find("rtc.execution_horizon"), std::string::npos);
  policy::Observation nan = with_rtc(ok, 0, 10);
  nan.rtc->prev_actions[1] = std::nanf("");
  EXPECT_NE(error_of(nan).find("rtc.prev_actions"), std::string::npos);
  policy::Observation weight = with_rtc(ok, 0, 10);
  weight.rtc->max_guidance_weight = 0;
  EXPECT_NE(error_of(weight).find("rtc.max_guidance_weight"), std::string::npos);
  policy::Observation threshold = observation(1);
  threshold.adaptive_threshold = -0.1f;
  EXPECT_NE(error_of(threshold).find("adaptive_threshold"), std::string::npos);
  EXPECT_EQ(error_of(with_rtc(ok, 2, 1)), "");  // delay past the leftover and horizon: allowed, as upstream
}

TEST(RealTimeChunking, LeftoverGoesBackToTheModelsOwnOutput) {
  // The target is the inverse of the output unnormalisation: a chunk fed back as its own leftover is the model's
  // normalised output again.
  const policy::Normalizer& post = demo().output_normalizer();
  std::vector<float> normalized;
  demo().set_debug_hook([&](const std::string& name, const Tensor& t) {
    if (name == "out.actions_normalized") normalized = t.to_f32();
  });
  const policy::ActionChunk chunk = predict_one(observation(8));
  demo().set_debug_hook({});
  std::vector<float> back = chunk.actions;
  post.invert_unnormalize(demo().spec().action_key, back.data(), int64_t(back.size()));
  ASSERT_EQ(back.size(), normalized.size());
  EXPECT_LT(max_abs_diff(back, normalized, int64_t(back.size())), 1e-5);
}
