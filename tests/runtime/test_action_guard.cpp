// Action guard: each limit alone, across rows and against the caller's history, NaN/Inf replacement, the order of
// the checks; the audit log's lines and concurrent appends.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <regex>
#include <thread>
#include <unistd.h>

#include "core/json_util.h"
#include "runtime/action_guard.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::runtime;
using policy::JointLimits;
namespace fs = std::filesystem;

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

JointLimits position(double lo, double hi) {
  JointLimits l;
  l.has_position_limits = true;
  l.min_position = lo;
  l.max_position = hi;
  return l;
}
JointLimits velocity(double v, JointLimits l = {}) {
  l.has_velocity_limits = true;
  l.max_velocity = v;
  return l;
}
JointLimits acceleration(double a, JointLimits l = {}) {
  l.has_acceleration_limits = true;
  l.max_acceleration = a;
  return l;
}

// One joint "j" at 10 Hz: dt = 0.1.
ActionGuard one_joint(JointLimits l) { return ActionGuard({"j"}, {l}, 10.0); }

void expect_violation(const GuardViolation& v, int64_t step, const std::string& limit, double requested,
                      double applied) {
  EXPECT_EQ(v.step, step);
  EXPECT_EQ(v.limit, limit);
  if (std::isnan(requested)) EXPECT_TRUE(std::isnan(v.requested));
  else EXPECT_NEAR(v.requested, requested, 1e-6);
  EXPECT_NEAR(v.applied, applied, 1e-6);
}

fs::path temp_path(const std::string& name) {
  fs::path dir = tether::testing::scratch_dir() / "guard";
  fs::create_directories(dir);
  fs::remove(dir / name);
  return dir / name;
}

std::vector<std::string> read_lines(const fs::path& path) {
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

}  // namespace

TEST(ActionGuard, ClampsPositionsAndReportsEachClamp) {
  const ActionGuard g({"a", "b"}, {position(-1, 1), position(0, 0.08)}, 15.0);
  std::vector<float> chunk = {1.5f, 0.05f,  // a above max
                              -2.f, -0.01f,  // both below min
                              0.f, 0.08f};
  const GuardReport r = g.apply(chunk.data(), 3, 2, nullptr, nullptr, nullptr);
  EXPECT_EQ(chunk, (std::vector<float>{1.f, 0.05f, -1.f, 0.f, 0.f, 0.08f}));
  EXPECT_TRUE(r.clamped);
  ASSERT_EQ(r.violations.size(), 3u);
  expect_violation(r.violations[0], 0, "position_max", 1.5, 1);
  EXPECT_EQ(r.violations[0].joint, "a");
  expect_violation(r.violations[1], 1, "position_min", -2, -1);
  expect_violation(r.violations[2], 1, "position_min", -0.01, 0);
  EXPECT_EQ(r.violations[2].joint, "b");
}

TEST(ActionGuard, LimitsVelocityAcrossRowsOnTheClampedValues) {
  const ActionGuard g = one_joint(velocity(1.0));  // at most 0.1 per step
  std::vector<float> chunk = {0.f, 0.5f, 0.55f, 0.3f};
  const GuardReport r = g.apply(chunk.data(), 4, 1, nullptr, nullptr, nullptr);
  // Row 0 has nothing before it; row 2 is checked against row 1's clamped 0.1, not the requested 0.5.
  EXPECT_FLOAT_EQ(chunk[0], 0.f);
  EXPECT_FLOAT_EQ(chunk[1], 0.1f);
  EXPECT_FLOAT_EQ(chunk[2], 0.2f);
  EXPECT_FLOAT_EQ(chunk[3], 0.3f);
  ASSERT_EQ(r.violations.size(), 2u);
  expect_violation(r.violations[0], 1, "velocity", 0.5, 0.1);
  expect_violation(r.violations[1], 2, "velocity", 0.55, 0.2);
}

TEST(ActionGuard, LimitsVelocityAgainstThePreviousCommand) {
  const ActionGuard g = one_joint(velocity(1.0));
  const float previous = 1.0f;
  std::vector<float> chunk = {0.f, -0.5f};
  const GuardReport r = g.apply(chunk.data(), 2, 1, &previous, nullptr, nullptr);
  EXPECT_FLOAT_EQ(chunk[0], 0.9f);
  EXPECT_FLOAT_EQ(chunk[1], 0.8f);
  ASSERT_EQ(r.violations.size(), 2u);
  expect_violation(r.violations[0], 0, "velocity", 0, 0.9);
}

TEST(ActionGuard, LimitsAccelerationWhenTwoEarlierCommandsAreKnown) {
  // max_acceleration 1 at dt 0.1: the per-step change may itself change by 1 * 0.1^2 = 0.01 per step.
  const ActionGuard g = one_joint(acceleration(1.0));
  const float before_previous = 0.f, previous = 0.1f;  // moving at 0.1 per step
  std::vector<float> chunk = {0.3f, 0.3f};
  GuardReport r = g.apply(chunk.data(), 2, 1, &previous, &before_previous, nullptr);
  EXPECT_NEAR(chunk[0], 0.21f, 1e-6);  // speeds up by at most 0.01 per step: 0.1 -> 0.11
  EXPECT_NEAR(chunk[1], 0.31f, 1e-6);  // nor slows down faster: 0.11 -> 0.10, not 0.09
  ASSERT_EQ(r.violations.size(), 2u);
  expect_violation(r.violations[0], 0, "acceleration", 0.3, 0.21);
  expect_violation(r.violations[1], 1, "acceleration", 0.3, 0.31);
}

TEST(ActionGuard, AccelerationNeedsTwoCommandsBeforeTheRow) {
  const ActionGuard g = one_joint(acceleration(1.0));
  const float previous = 0.f;
  // Row 0 has one command before it (no check); row 1 has previous and row 0: 0.5 - 0.5 vs 0.5 - 0: clamped.
  std::vector<float> chunk = {0.5f, 0.5f};
  GuardReport r = g.apply(chunk.data(), 2, 1, &previous, nullptr, nullptr);
  EXPECT_FLOAT_EQ(chunk[0], 0.5f);
  EXPECT_NEAR(chunk[1], 0.99f, 1e-6);  // keeps moving: 0.5 + 0.5 - 0.01
  ASSERT_EQ(r.violations.size(), 1u);
  expect_violation(r.violations[0], 1, "acceleration", 0.5, 0.99);

  // Without any history, rows 0 and 1 are free; row 2 is the first one checked.
  chunk = {0.f, 0.5f, 0.5f};
  r = g.apply(chunk.data(), 3, 1, nullptr, nullptr, nullptr);
  EXPECT_FLOAT_EQ(chunk[1], 0.5f);
  EXPECT_NEAR(chunk[2], 0.99f, 1e-6);
  ASSERT_EQ(r.violations.size(), 1u);
  EXPECT_EQ(r.violations[0].step, 2);
}

TEST(ActionGuard, ReplacesNonFiniteWithTheLastSafeCommand) {
  const ActionGuard g = one_joint(position(-1, 3));
  const float previous = 0.25f, fallback = 0.75f;

  std::vector<float> chunk = {0.5f, kNaN, kInf};  // earlier row in the chunk wins
  GuardReport r = g.apply(chunk.data(), 3, 1, &previous, nullptr, &fallback);
  EXPECT_EQ(chunk, (std::vector<float>{0.5f, 0.5f, 0.5f}));
  ASSERT_EQ(r.violations.size(), 2u);
  expect_violation(r.violations[0], 1, "non_finite", kNaN, 0.5);
  EXPECT_TRUE(std::isinf(r.violations[1].requested));

  chunk = {-kInf};  // then `previous`
  r = g.apply(chunk.data(), 1, 1, &previous, nullptr, &fallback);
  EXPECT_FLOAT_EQ(chunk[0], 0.25f);

  chunk = {kNaN};  // then the fallback
  r = g.apply(chunk.data(), 1, 1, nullptr, nullptr, &fallback);
  EXPECT_FLOAT_EQ(chunk[0], 0.75f);

  chunk = {kNaN};  // then the midpoint of the position limits
  r = g.apply(chunk.data(), 1, 1, nullptr, nullptr, nullptr);
  EXPECT_FLOAT_EQ(chunk[0], 1.f);

  chunk = {kNaN};  // a non-finite `previous` or fallback is no safe command
  const float bad = kNaN;
  r = g.apply(chunk.data(), 1, 1, &bad, nullptr, &bad);
  EXPECT_FLOAT_EQ(chunk[0], 1.f);

  const ActionGuard free = one_joint({});  // no position limits: 0
  chunk = {kNaN, 2.f};
  r = free.apply(chunk.data(), 2, 1, nullptr, nullptr, nullptr);
  EXPECT_EQ(chunk, (std::vector<float>{0.f, 2.f}));
  ASSERT_EQ(r.violations.size(), 1u);
}

TEST(ActionGuard, PositionLimitsWinOverRateLimits) {
  // Previous command outside the range: reaching the range needs a faster move than max_velocity allows.
  const ActionGuard g = one_joint(velocity(1.0, position(0.5, 1.0)));
  const float previous = 0.f;
  std::vector<float> chunk = {0.6f};
  const GuardReport r = g.apply(chunk.data(), 1, 1, &previous, nullptr, nullptr);
  EXPECT_FLOAT_EQ(chunk[0], 0.5f);
  ASSERT_EQ(r.violations.size(), 2u);
  expect_violation(r.violations[0], 0, "velocity", 0.6, 0.1);
  expect_violation(r.violations[1], 0, "position_min", 0.1, 0.5);
}

TEST(ActionGuard, ReplacedValuesAreCheckedLikeAnyOther) {
  // A fallback outside the range is replaced first, then clamped into it.
  const ActionGuard g = one_joint(position(-1, 1));
  const float fallback = 5.f;
  std::vector<float> chunk = {kNaN};
  const GuardReport r = g.apply(chunk.data(), 1, 1, nullptr, nullptr, &fallback);
  EXPECT_FLOAT_EQ(chunk[0], 1.f);
  ASSERT_EQ(r.violations.size(), 2u);
  EXPECT_EQ(r.violations[0].limit, "non_finite");
  expect_violation(r.violations[1], 0, "position_max", 5, 1);
}

TEST(ActionGuard, LeavesAChunkInsideTheLimitsUntouched) {
  // Franka-like joint at 15 Hz: a smooth sine well inside position, velocity and acceleration limits, plus a joint
  // without limits carrying large values.
  const ActionGuard g({"j", "free"}, {acceleration(15.0, velocity(2.175, position(-2.8973, 2.8973))), {}}, 15.0);
  std::vector<float> chunk;
  for (int i = 0; i < 50; ++i) {
    chunk.push_back(float(0.8 * std::sin(0.05 * i)));
    chunk.push_back(float(1000 * i));
  }
  const std::vector<float> original = chunk;
  const float before_previous = float(0.8 * std::sin(-0.1)), previous = float(0.8 * std::sin(-0.05));
  const float prev2[2] = {before_previous, 0.f}, prev1[2] = {previous, 0.f};
  const GuardReport r = g.apply(chunk.data(), 50, 2, prev1, prev2, nullptr);
  EXPECT_FALSE(r.clamped);
  EXPECT_TRUE(r.violations.empty());
  EXPECT_EQ(0, std::memcmp(chunk.data(), original.data(), chunk.size() * sizeof(float)));
}

TEST(ActionGuard, GuardingAGuardedChunkChangesNothing) {
  const ActionGuard g = one_joint(acceleration(20.0, velocity(2.61, position(-10, 10))));
  std::vector<float> chunk;
  for (int i = 0; i < 40; ++i) chunk.push_back(float(3.0 * std::sin(0.7 * i)));  // far too fast
  const float previous = 0.f;
  EXPECT_TRUE(g.apply(chunk.data(), 40, 1, &previous, nullptr, nullptr).clamped);
  const std::vector<float> once = chunk;
  const GuardReport again = g.apply(chunk.data(), 40, 1, &previous, nullptr, nullptr);
  EXPECT_TRUE(again.violations.empty()) << again.violations.front().limit << " at " << again.violations.front().step;
  EXPECT_EQ(chunk, once);
}

TEST(ActionGuard, RejectsMismatchedShapesAndLimits) {
  const ActionGuard g = one_joint(position(0, 1));
  std::vector<float> chunk(4, 0.f);
  EXPECT_THROW(g.apply(chunk.data(), 2, 2, nullptr, nullptr, nullptr), Error);
  EXPECT_THROW(ActionGuard({"a", "b"}, {JointLimits{}}, 10.0), Error);
  EXPECT_THROW(ActionGuard({"a"}, {velocity(1.0)}, 0.0), Error);
  EXPECT_THROW(ActionGuard({"a"}, {position(1, 0)}, 10.0), Error);
  EXPECT_NO_THROW(ActionGuard({"a"}, {position(0, 1)}, 0.0));  // positions need no rate
}

TEST(AuditLog, WritesOneParseableLinePerViolation) {
  const fs::path path = temp_path("audit.jsonl");
  AuditLog log(path.string());
  const std::vector<GuardViolation> v = {{0, "elbow", "velocity", 1.25, 1.1}, {3, "gripper", "non_finite", kNaN, 0.5}};
  log.append("req-1", "ep-7", v);
  log.append("req-2", "ep-7", {});  // nothing to write
  const auto lines = read_lines(path);
  ASSERT_EQ(lines.size(), 2u);
  const std::regex iso(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z)");
  for (size_t i = 0; i < 2; ++i) {
    const Json j = Json::parse(lines[i]);
    EXPECT_TRUE(std::regex_match(j.at("time").get<std::string>(), iso)) << j.at("time");
    EXPECT_EQ(j.at("request_id"), "req-1");
    EXPECT_EQ(j.at("episode_id"), "ep-7");
    EXPECT_EQ(j.at("step"), v[i].step);
    EXPECT_EQ(j.at("joint"), v[i].joint);
    EXPECT_EQ(j.at("limit"), v[i].limit);
    EXPECT_EQ(j.at("applied").get<double>(), v[i].applied);
  }
  EXPECT_EQ(Json::parse(lines[0]).at("requested").get<double>(), 1.25);
  EXPECT_TRUE(Json::parse(lines[1]).at("requested").is_null());
  EXPECT_EQ(log.write_errors(), 0);

  EXPECT_FALSE(Json::parse(lines[0]).contains("embodiment")) << "a model without embodiment tags";

  // A second log on the same file appends after the first one's lines; a GR00T robot's lines name its embodiment.
  AuditLog(path.string()).append("req-3", "ep-8", {v[0]}, "unitree_g1");
  ASSERT_EQ(read_lines(path).size(), 3u);
  EXPECT_EQ(Json::parse(read_lines(path)[2]).at("embodiment"), "unitree_g1");
}

TEST(AuditLog, ConcurrentAppendsProduceWholeLines) {
  const fs::path path = temp_path("audit_concurrent.jsonl");
  AuditLog log(path.string());
  constexpr int kThreads = 8, kAppends = 200, kPerBatch = 5;
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t)
    threads.emplace_back([&, t] {
      std::vector<GuardViolation> batch;
      for (int k = 0; k < kPerBatch; ++k)
        batch.push_back({k, "joint_with_a_long_name_" + std::to_string(t), "position_max", 1.0 + t, 1.0});
      for (int i = 0; i < kAppends; ++i) log.append("req-" + std::to_string(t) + "-" + std::to_string(i), "ep", batch);
    });
  for (auto& th : threads) th.join();
  const auto lines = read_lines(path);
  ASSERT_EQ(lines.size(), size_t(kThreads * kAppends * kPerBatch));
  std::map<std::string, int> per_request;
  for (const auto& line : lines) {
    const Json j = Json::parse(line);  // throws on a torn or interleaved line
    ++per_request[j.at("request_id").get<std::string>()];
  }
  EXPECT_EQ(per_request.size(), size_t(kThreads * kAppends));
  for (const auto& [id, n] : per_request) EXPECT_EQ(n, kPerBatch) << id;
  EXPECT_EQ(log.write_errors(), 0);
}

TEST(AuditLog, OpeningFailureNamesThePathAndWriteFailuresAreCounted) {
  try {
    AuditLog log("/nonexistent_dir/audit.jsonl");
    ADD_FAILURE() << "no error";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::io);
    EXPECT_NE(std::string(e.what()).find("/nonexistent_dir/audit.jsonl"), std::string::npos);
  }
  if (!fs::exists("/dev/full")) GTEST_SKIP() << "no /dev/full";
  AuditLog full("/dev/full");  // every write fails with ENOSPC
  EXPECT_NO_THROW(full.append("r", "e", {{0, "j", "velocity", 1, 0}}));
  EXPECT_NO_THROW(full.append("r", "e", {{0, "j", "velocity", 1, 0}}));
  EXPECT_EQ(full.write_errors(), 2);
}

TEST(AuditLog, InvalidUtf8InIdsDoesNotThrow) {
  const fs::path path = temp_path("audit_utf8.jsonl");
  AuditLog log(path.string());
  EXPECT_NO_THROW(log.append(std::string("req-\xff\xfe"), "ep", {{0, "j", "velocity", 1, 0}}));
  const auto lines = read_lines(path);
  ASSERT_EQ(lines.size(), 1u);
  EXPECT_TRUE(Json::accept(lines[0])) << lines[0];
}
