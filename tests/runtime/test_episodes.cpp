// Episode bookkeeping: advancing a cached chunk by elapsed control steps, the observation distance behind the
// similarity skip, and the bounded episode store.
#include <gtest/gtest.h>

#include <cmath>

#include "runtime/episodes.h"

using namespace tether;
using namespace tether::runtime;
using namespace std::chrono_literals;

TEST(Episodes, ElapsedSteps) {
  const auto t0 = SteadyClock::now();
  EXPECT_EQ(elapsed_steps(t0, t0 + 99ms, 10.0), 0);
  EXPECT_EQ(elapsed_steps(t0, t0 + 100ms, 10.0), 1);
  EXPECT_EQ(elapsed_steps(t0, t0 + 1050ms, 30.0), 31);
  EXPECT_EQ(elapsed_steps(t0, t0 + 5s, 0.0), 0);   // unknown rate: no shift
  EXPECT_EQ(elapsed_steps(t0 + 1s, t0, 10.0), 0);  // never negative
}

TEST(Episodes, AdvanceDropsExecutedRowsAndHoldsTheLast) {
  TimedChunk c;
  c.rows = 4;
  c.dim = 2;
  c.actions = {0, 10, 1, 11, 2, 12, 3, 13};
  EXPECT_EQ(advance_chunk(c, 0), c.actions);
  EXPECT_EQ(advance_chunk(c, 1), (std::vector<float>{1, 11, 2, 12, 3, 13, 3, 13}));
  EXPECT_EQ(advance_chunk(c, 3), (std::vector<float>{3, 13, 3, 13, 3, 13, 3, 13}));
  EXPECT_EQ(advance_chunk(c, 100), (std::vector<float>{3, 13, 3, 13, 3, 13, 3, 13}));
}

namespace {

vision::Image frame(uint8_t value, int h = 4, int w = 5) {
  vision::Image img;
  img.height = h;
  img.width = w;
  img.rgb.assign(std::size_t(h * w * 3), value);
  return img;
}

}  // namespace

TEST(Episodes, ObservationDistance) {
  EpisodeState ref;
  policy::Observation obs;
  obs.instruction = "pick";
  obs.images["cam"] = frame(100);
  EXPECT_TRUE(std::isinf(observation_distance(obs, {0.f, 0.f}, ref)));  // no reference yet

  ref.has_reference = true;
  ref.reference_instruction = "pick";
  ref.reference_state = {0.f, 0.f};
  ref.reference_images["cam"] = frame(100);
  EXPECT_EQ(observation_distance(obs, {0.f, 0.f}, ref), 0.0);
  EXPECT_NEAR(observation_distance(obs, {0.f, -0.25f}, ref), 0.25, 1e-7);  // largest state change
  obs.images["cam"] = frame(151);
  EXPECT_NEAR(observation_distance(obs, {0.f, 0.f}, ref), 51.0 / 255.0, 1e-12);  // mean pixel change / 255
  obs.images["cam"].rgb[0] = 0;  // one pixel channel far off moves the mean a little
  EXPECT_NEAR(observation_distance(obs, {0.f, 0.f}, ref), (51.0 * 59 + 100) / (255.0 * 60), 1e-12);

  obs.images["cam"] = frame(100, 4, 6);
  EXPECT_TRUE(std::isinf(observation_distance(obs, {0.f, 0.f}, ref)));  // a different frame size
  obs.images["cam"] = frame(100);
  obs.instruction = "place";
  EXPECT_TRUE(std::isinf(observation_distance(obs, {0.f, 0.f}, ref)));  // a new task is never "similar"
  obs.instruction = "pick";
  obs.images["other"] = frame(100);
  EXPECT_TRUE(std::isinf(observation_distance(obs, {0.f, 0.f}, ref)));  // a different camera set
}

TEST(Episodes, StoreKeepsEpisodesApartAndForgetsTheOldest) {
  EpisodeStore store(2);
  auto a = store.get("a");
  a->state.similar_skips = 5;
  EXPECT_EQ(store.get("a")->state.similar_skips, 5);
  EXPECT_EQ(store.get("b")->state.similar_skips, 0);
  store.get("a");  // a is now more recent than b
  store.get("c");  // evicts b
  EXPECT_EQ(store.size(), 2u);
  EXPECT_EQ(store.get("a")->state.similar_skips, 5);
  EXPECT_EQ(store.get("b")->state.similar_skips, 0);  // b starts over
}
