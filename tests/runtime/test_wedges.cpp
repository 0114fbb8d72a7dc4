// The synchronous wedge logic: binding to a model (embodiment and safety-config checks), the similarity skip and
// its counter, last good chunks (late answers never replace newer ones), the embodiment map, and the guard's
// history across requests of one episode.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <thread>

#include "core/error.h"
#include "runtime/wedges.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::runtime;
using namespace std::chrono_literals;
namespace fs = std::filesystem;

namespace {

models::ModelSpec spec(int64_t dim = 2, int64_t rows = 4) {
  models::ModelSpec s;
  s.action_dim = dim;
  s.chunk_size = rows;
  return s;
}

policy::Embodiment two_joint_arm() {
  policy::Embodiment e;
  e.name = "arm";
  e.control_rate_hz = 10;
  e.joints = {"a", "b"};
  e.range_min = {-1, 0};
  e.range_max = {1, 10};
  e.limits.resize(2);
  for (auto& l : e.limits) {
    l.has_position_limits = true;
    l.min_position = -5;
    l.max_position = 5;
    l.has_velocity_limits = true;
    l.max_velocity = 10;  // 1 per step at 10 Hz
  }
  return e;
}

std::string temp_path(const std::string& name) {
  return (tether::testing::scratch_dir() / ("wedges_" + name)).string();
}

policy::Observation observation(float state0, uint8_t pixel) {
  policy::Observation o;
  o.instruction = "pick";
  o.state = {state0, 0.f};
  vision::Image img;
  img.height = 2;
  img.width = 2;
  img.rgb.assign(12, pixel);
  o.images["cam"] = img;
  return o;
}

}  // namespace

TEST(Wedges, BindChecksTheEmbodimentAgainstTheModel) {
  WedgeOptions o;
  o.embodiment = two_joint_arm();
  o.audit_log = temp_path("audit1.jsonl");
  Wedges w(o);
  try {
    w.bind_model(spec(3), false);
    FAIL() << "a 2-joint embodiment bound to a 3-action model";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("2 joints"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("3 action values"), std::string::npos) << e.what();
  }
  Wedges ok(o);
  ok.bind_model(spec(2), false);
  EXPECT_TRUE(ok.guard_enabled());
  EXPECT_EQ(ok.control_rate_hz(), 10);
  EXPECT_EQ(ok.joint_names(), (std::vector<std::string>{"a", "b"}));
}

TEST(Wedges, ControlRatePrecedence) {
  WedgeOptions o;
  EXPECT_EQ(Wedges(o).control_rate_hz(), kDefaultControlRateHz);
  o.embodiment = two_joint_arm();
  EXPECT_EQ(Wedges(o).control_rate_hz(), 10);
  o.safety = policy::SafetyConfig{};
  o.safety->control_rate_hz = 20;
  EXPECT_EQ(Wedges(o).control_rate_hz(), 20);
  o.control_rate_hz = 40;
  EXPECT_EQ(Wedges(o).control_rate_hz(), 40);
}

TEST(Wedges, SimilaritySkipAtMostKInARowThenTheModelRuns) {
  WedgeOptions o;
  o.similarity_threshold = 0.05;
  o.max_similar_skips = 2;
  Wedges w(o);
  w.bind_model(spec(), false);
  auto ep = w.episodes().get("e");
  const auto obs = observation(0.f, 100);
  const std::vector<float> norm = {0.f, 0.f};
  WedgeReport r0;
  EXPECT_FALSE(w.try_skip(*ep, obs, norm, r0));  // nothing cached yet

  std::vector<float> chunk = {0, 0, 1, 1, 2, 2, 3, 3};
  w.on_model_chunk(*ep, chunk, SteadyClock::now(), &obs, norm);
  for (int i = 1; i <= 2; ++i) {
    WedgeReport r;
    const auto got = w.try_skip(*ep, observation(0.f, 101), {0.01f, 0.f}, r);
    ASSERT_TRUE(got) << i;
    EXPECT_TRUE(r.skipped);
    EXPECT_EQ(r.similar_skips, i);
    EXPECT_EQ(r.source, ActionSource::cache);
    EXPECT_NEAR(r.similarity_distance, 0.01, 1e-6);
  }
  WedgeReport r3;
  EXPECT_FALSE(w.try_skip(*ep, obs, norm, r3));  // K reached: the model must run
  WedgeReport far;
  w.on_model_chunk(*ep, chunk, SteadyClock::now(), &obs, norm);  // resets the counter
  EXPECT_FALSE(w.try_skip(*ep, observation(0.f, 100), {0.2f, 0.f}, far));
  EXPECT_NEAR(far.similarity_distance, 0.2, 1e-6);
}

TEST(Wedges, LateAnswersNeverReplaceNewerChunks) {
  Wedges w(WedgeOptions{});
  w.bind_model(spec(), false);
  auto ep = w.episodes().get("");
  const auto now = SteadyClock::now();
  std::vector<float> newer = {1, 1, 1, 1, 1, 1, 1, 1}, older = {9, 9, 9, 9, 9, 9, 9, 9};
  w.on_model_chunk(*ep, newer, now, nullptr, {});
  w.on_model_chunk(*ep, older, now - 1s, nullptr, {});
  WedgeReport r;
  EXPECT_EQ(*w.last_good(*ep, r), newer);
  EXPECT_EQ(r.source, ActionSource::last_good);
  EXPECT_FALSE(w.last_good(*w.episodes().get("other"), r));  // episodes do not share chunks
}

TEST(Wedges, AnEndedEpisodeStartsFromNothing) {
  WedgeOptions o;
  o.similarity_threshold = 0.05;
  o.max_similar_skips = 2;
  Wedges w(o);
  w.bind_model(spec(), false);
  const auto obs = observation(0.f, 100);
  const std::vector<float> norm = {0.f, 0.f};
  std::vector<float> chunk = {0, 0, 1, 1, 2, 2, 3, 3};
  auto held = w.episodes().get("ep");
  w.on_model_chunk(*held, chunk, SteadyClock::now(), &obs, norm);
  w.on_model_chunk(*w.episodes().get("other"), chunk, SteadyClock::now(), &obs, norm);
  EXPECT_TRUE(w.episodes().end("ep"));
  EXPECT_FALSE(w.episodes().end("ep"));
  auto fresh = w.episodes().get("ep");
  WedgeReport r;
  EXPECT_FALSE(w.last_good(*fresh, r));           // no last good chunk
  EXPECT_FALSE(w.try_skip(*fresh, obs, norm, r));  // no skip cache
  EXPECT_TRUE(fresh->state.last_sent.empty());     // no guard history
  // A request still holding the old episode finishes against it; what it records does not reach the new one.
  w.on_model_chunk(*held, chunk, SteadyClock::now(), &obs, norm);
  EXPECT_FALSE(w.last_good(*w.episodes().get("ep"), r));
  EXPECT_TRUE(w.last_good(*w.episodes().get("other"), r));  // other episodes are untouched
}

TEST(Wedges, LastGoodChunkIsAdvancedByElapsedSteps) {
  WedgeOptions o;
  o.control_rate_hz = 100;
  Wedges w(o);
  w.bind_model(spec(), false);
  auto ep = w.episodes().get("");
  std::vector<float> chunk = {0, 0, 1, 1, 2, 2, 3, 3};
  w.on_model_chunk(*ep, chunk, SteadyClock::now() - 25ms, nullptr, {});
  WedgeReport r;
  const auto got = *w.last_good(*ep, r);
  EXPECT_GE(r.advanced_steps, 2);
  EXPECT_EQ(got.front(), float(std::min<int64_t>(r.advanced_steps, 3)));
  EXPECT_EQ(got.back(), 3.f);  // the last row is held
}

TEST(Wedges, EmbodimentMapsNormalisedOutputOnlyWithoutActionStats) {
  WedgeOptions o;
  o.embodiment = two_joint_arm();
  o.audit_log = temp_path("audit2.jsonl");
  Wedges mapped(o), plain(o);
  mapped.bind_model(spec(2, 1), /*actions_normalized=*/true);
  plain.bind_model(spec(2, 1), false);
  std::vector<float> a = {-1.f, 1.f}, b = a;
  mapped.map_output(a);
  plain.map_output(b);
  EXPECT_EQ(a, (std::vector<float>{-1.f, 10.f}));
  EXPECT_EQ(b, (std::vector<float>{-1.f, 1.f}));
}

TEST(Wedges, EmbodimentCutsAPaddedOutputToItsJoints) {
  WedgeOptions o;
  o.embodiment = two_joint_arm();
  o.audit_log = temp_path("audit_cut.jsonl");
  // A base checkpoint's padded action (action_dim = max_action_dim): the first two values of each row are the arm's.
  models::ModelSpec padded = spec(5, 2);
  padded.max_action_dim = 5;
  Wedges w(o);
  w.bind_model(padded, /*actions_normalized=*/true);
  EXPECT_EQ(w.action_dim(), 2);
  EXPECT_EQ(w.config_json()["embodiment"]["model_action_dim"], 5);
  std::vector<float> a = {-1.f, 1.f, 7, 7, 7, 0.f, -1.f, 7, 7, 7};
  w.map_output(a);
  EXPECT_EQ(a, (std::vector<float>{-1.f, 10.f, 0.f, 0.f}));
  // RTC's leftover goes back through the inverse of the range map.
  w.unmap_output(a);
  EXPECT_EQ(a, (std::vector<float>{-1.f, 1.f, 0.f, -1.f}));
  // Not padded (action_dim < max_action_dim), or more joints than values: refused, naming both counts.
  models::ModelSpec unpadded = spec(5, 2);
  unpadded.max_action_dim = 32;
  for (const models::ModelSpec& s : {unpadded, spec(1, 2)}) {
    Wedges refused(o);
    try {
      refused.bind_model(s, false);
      FAIL() << "bound to " << s.action_dim << " action values";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("2 joints, the model outputs " + std::to_string(s.action_dim)),
                std::string::npos)
          << e.what();
    }
  }
  EXPECT_EQ(embodiment_action_dim(*o.embodiment, padded), 2);
  // RTC needs the model's whole output back.
  o.sampler.rtc = true;
  Wedges rtc(o);
  EXPECT_THROW(rtc.bind_model(padded, false), Error);
}

TEST(Wedges, GuardUsesTheEpisodesLastSentChunkAndAudits) {
  WedgeOptions o;
  o.embodiment = two_joint_arm();
  // 10 Hz: the calls below are well under 100 ms apart, so row 0 of the last chunk is the command in execution.
  o.audit_log = temp_path("audit3.jsonl");
  fs::remove(o.audit_log);
  Wedges w(o);
  w.bind_model(spec(2, 2), false);
  auto ep = w.episodes().get("ep");
  std::vector<float> first = {0, 0, 0.5f, 0.5f};
  WedgeReport r1;
  w.guard(*ep, first, 2, {0, 0}, "req-1", "ep", r1);
  EXPECT_FALSE(r1.guard.clamped);
  // The next chunk starts 4 away from the command in execution: the velocity limit (1 per step) applies across
  // requests, and NaN becomes the last safe command.
  std::vector<float> second = {4, NAN, 4, 0};
  WedgeReport r2;
  w.guard(*ep, second, 2, {0, 0}, "req-2", "ep", r2);
  EXPECT_TRUE(r2.guard.clamped);
  EXPECT_FLOAT_EQ(second[0], 1.f);
  EXPECT_FLOAT_EQ(second[1], 0.f);
  EXPECT_FLOAT_EQ(second[2], 2.f);
  std::ifstream in(o.audit_log);
  std::string line;
  int lines = 0;
  while (std::getline(in, line)) {
    EXPECT_NE(line.find("\"request_id\":\"req-2\""), std::string::npos) << line;
    ++lines;
  }
  EXPECT_EQ(lines, int(r2.guard.violations.size()));
  // Another episode has no history: the same chunk only meets position limits and row-to-row velocity.
  std::vector<float> third = {4, 0, 4, 0};
  WedgeReport r3;
  w.guard(*w.episodes().get("fresh"), third, 2, {0, 0}, "req-3", "fresh", r3);
  EXPECT_FALSE(r3.guard.clamped);
  fs::remove(o.audit_log);
}

TEST(Wedges, ResponseFieldsOnlyForEnabledWedges) {
  Wedges none(WedgeOptions{});
  none.bind_model(spec(), false);
  const Json f = none.response_fields(WedgeReport{});
  EXPECT_EQ(f.size(), 1u);
  EXPECT_EQ(f["action_source"], "model");
  WedgeOptions o;
  o.deadline_ms = 50;
  o.sampler.adaptive_threshold = 0.1f;
  o.max_consecutive_crashes = 3;
  o.inject_latency_ms = 5;
  Wedges some(o);
  some.bind_model(spec(), false);
  WedgeReport r;
  r.deadline_exceeded = true;
  r.denoise_steps_used = 4;
  const Json g = some.response_fields(r);
  EXPECT_EQ(g["deadline_exceeded"], true);
  EXPECT_EQ(g["denoise_steps_used"], 4);
  EXPECT_EQ(g["circuit_state"], "closed");
  EXPECT_EQ(g["injected_latency_ms"], 5.0);
  EXPECT_FALSE(g.contains("guard_clamped"));
  EXPECT_FALSE(g.contains("fallback_used"));
}
