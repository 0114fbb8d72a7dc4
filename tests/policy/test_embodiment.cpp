// Embodiment presets and files, the safety config and its per-joint overrides: every preset's figures, and an error
// naming the file and field for each kind of bad file.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <functional>
#include <fstream>
#include <unistd.h>

#include "core/error.h"
#include "policy/embodiment.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::policy;
namespace fs = std::filesystem;

namespace {

const std::string kPresets = std::string(TETHER_SOURCE_DIR) + "/models/embodiments";

fs::path temp_dir() {
  fs::path dir = tether::testing::scratch_dir() / "embodiment";
  fs::create_directories(dir);
  return dir;
}

std::string write_file(const std::string& name, const std::string& text) {
  const fs::path path = temp_dir() / name;
  std::ofstream(path) << text;
  return path.string();
}

// The error a loader throws, with its code; fails the test when nothing is thrown.
Error error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e;
  }
  ADD_FAILURE() << "no tether::Error thrown";
  return Error(ErrorCode::internal, "");
}

const char* kValidJoint = R"({"name": "a", "min": -1, "max": 1, "max_velocity": 2})";

std::string embodiment_json(const std::string& joints, const std::string& extra = "") {
  return R"({"name": "arm", "units": "rad", "control_rate_hz": 10, )" + extra + R"("joints": [)" + joints + "]}";
}

}  // namespace

TEST(Embodiment, EveryPresetLoadsWithSaneFigures) {
  EXPECT_EQ(embodiment_presets(kPresets), (std::vector<std::string>{"franka", "quadcopter", "so100", "ur5"}));
  for (const auto& name : embodiment_presets(kPresets)) {
    SCOPED_TRACE(name);
    const Embodiment e = load_embodiment_preset(name, kPresets);
    EXPECT_EQ(e.name, name);
    EXPECT_FALSE(e.description.empty());
    EXPECT_FALSE(e.units.empty());
    EXPECT_FALSE(e.source.empty());
    EXPECT_GE(e.control_rate_hz, 10);
    EXPECT_LE(e.control_rate_hz, 50);
    ASSERT_FALSE(e.joints.empty());
    ASSERT_EQ(e.range_min.size(), e.joints.size());
    ASSERT_EQ(e.range_max.size(), e.joints.size());
    ASSERT_EQ(e.limits.size(), e.joints.size());
    for (size_t j = 0; j < e.joints.size(); ++j) {
      SCOPED_TRACE(e.joints[j]);
      const JointLimits& l = e.limits[j];
      EXPECT_LT(e.range_min[j], e.range_max[j]);
      EXPECT_TRUE(l.has_position_limits);
      EXPECT_LT(l.min_position, l.max_position);
      EXPECT_TRUE(l.has_velocity_limits);
      EXPECT_GT(l.max_velocity, 0);
      // One control step's worth of velocity limit is a fraction of the joint's range, else the limit is no limit.
      EXPECT_LT(l.max_velocity / e.control_rate_hz, 0.5 * (l.max_position - l.min_position));
      if (l.has_acceleration_limits) {
        EXPECT_GT(l.max_acceleration, 0);
      }
    }
  }
}

TEST(Embodiment, PresetFiguresMatchTheirSources) {
  const Embodiment franka = load_embodiment_preset("franka", kPresets);
  ASSERT_EQ(franka.joints.size(), 8u);
  EXPECT_EQ(franka.joints[0], "panda_joint1");
  EXPECT_EQ(franka.joints[7], "gripper");
  EXPECT_EQ(franka.control_rate_hz, 15);
  EXPECT_DOUBLE_EQ(franka.limits[3].min_position, -3.0718);
  EXPECT_DOUBLE_EQ(franka.limits[3].max_position, -0.0698);
  EXPECT_DOUBLE_EQ(franka.limits[5].max_position, 3.7525);
  EXPECT_DOUBLE_EQ(franka.limits[0].max_velocity, 2.175);
  EXPECT_DOUBLE_EQ(franka.limits[6].max_velocity, 2.61);
  EXPECT_DOUBLE_EQ(franka.limits[1].max_acceleration, 7.5);
  EXPECT_DOUBLE_EQ(franka.range_max[7], 0.08);
  EXPECT_FALSE(franka.limits[7].has_acceleration_limits);

  const Embodiment ur5 = load_embodiment_preset("ur5", kPresets);
  ASSERT_EQ(ur5.joints.size(), 7u);
  for (size_t j = 0; j < 6; ++j) {
    EXPECT_NEAR(ur5.limits[j].max_position, 2 * M_PI, 1e-5);
    EXPECT_NEAR(ur5.limits[j].min_position, -2 * M_PI, 1e-5);
    EXPECT_NEAR(ur5.limits[j].max_velocity, M_PI, 1e-5);  // 180 degrees/s
  }
  EXPECT_EQ(ur5.range_min[6], 0);
  EXPECT_EQ(ur5.range_max[6], 1);

  const Embodiment so100 = load_embodiment_preset("so100", kPresets);
  EXPECT_EQ(so100.joints, (std::vector<std::string>{"shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex",
                                                    "wrist_roll", "gripper"}));
  EXPECT_EQ(so100.control_rate_hz, 30);
  EXPECT_EQ(so100.range_min[0], -100);
  EXPECT_EQ(so100.range_max[4], 100);
  EXPECT_EQ(so100.range_min[5], 0);
  EXPECT_EQ(so100.range_max[5], 100);

  const Embodiment quad = load_embodiment_preset("quadcopter", kPresets);
  EXPECT_EQ(quad.joints, (std::vector<std::string>{"vx", "vy", "vz", "yaw_rate"}));
  EXPECT_EQ(quad.control_rate_hz, 50);
}

TEST(Embodiment, MapsNormalizedOutputToTheActionRange) {
  const Embodiment so100 = load_embodiment_preset("so100", kPresets);
  std::vector<float> a = {-1, 0, 1, 0.5f, -0.5f, -1,  // row 0
                          1, 1, 1, 1, 1, 1};          // row 1
  so100.map_normalized_to_range(a.data(), 2);
  EXPECT_EQ(a[0], -100);
  EXPECT_EQ(a[1], 0);
  EXPECT_EQ(a[2], 100);
  EXPECT_EQ(a[3], 50);
  EXPECT_EQ(a[4], -50);
  EXPECT_EQ(a[5], 0);  // gripper 0..100
  EXPECT_EQ(a[11], 100);
}

TEST(Embodiment, CustomFileDefaultsPositionLimitsToTheRange) {
  const std::string path = write_file("custom.json", embodiment_json(
      R"({"name": "a", "min": -1, "max": 2}, {"name": "b", "min": 0, "max": 1, "min_position": 0.2,
          "max_position": 0.8, "max_velocity": 0.5, "max_acceleration": 3})"));
  const Embodiment e = load_embodiment_file(path);
  EXPECT_EQ(e.joints, (std::vector<std::string>{"a", "b"}));
  EXPECT_TRUE(e.limits[0].has_position_limits);
  EXPECT_EQ(e.limits[0].min_position, -1);
  EXPECT_EQ(e.limits[0].max_position, 2);
  EXPECT_FALSE(e.limits[0].has_velocity_limits);
  EXPECT_FALSE(e.limits[0].has_acceleration_limits);
  EXPECT_EQ(e.limits[1].min_position, 0.2);
  EXPECT_EQ(e.limits[1].max_velocity, 0.5);
  EXPECT_EQ(e.limits[1].max_acceleration, 3);
  EXPECT_TRUE(e.description.empty());
}

TEST(Embodiment, EachKindOfBadFileNamesTheField) {
  const std::string joint = kValidJoint;
  const std::vector<std::pair<std::string, std::string>> cases = {
      {embodiment_json(joint + R"(, {"name": "b", "min": 0, "max": 1},
                        {"name": "c", "min": 0, "max": 1, "max_velocity": -1})"),
       "joints[2].max_velocity: expected a positive number, got -1"},
      {R"({"name": "arm", "units": "rad", "control_rate_hz": 0, "joints": [)" + joint + "]}",
       "control_rate_hz: expected a positive number, got 0"},
      {R"({"name": "arm", "units": "rad", "joints": [)" + joint + "]}", "control_rate_hz: missing"},
      {R"({"name": "arm", "control_rate_hz": 10, "joints": [)" + joint + "]}", "units: missing"},
      {embodiment_json(joint, R"("control_rate": 10, )"), ": unknown key 'control_rate'"},
      {embodiment_json(R"({"name": "a", "min": -1, "max": 1, "max_velocty": 2})"),
       "joints[0]: unknown key 'max_velocty'"},
      {embodiment_json(joint + ", " + joint), "joints[1].name: duplicate joint name 'a' (also joints[0])"},
      {embodiment_json(R"({"name": "a", "min": 1, "max": 0})"), "joints[0].max: expected at least min (1), got 0"},
      {embodiment_json(R"({"name": "a", "min": 0, "max": 1, "min_position": 0.5, "max_position": 0.4})"),
       "joints[0].max_position: expected at least min_position (0.5), got 0.4"},
      {embodiment_json(R"({"name": "a", "min": 0, "max": 1, "min_position": 0.5})"),
       "joints[0].max_position: missing (min_position is given)"},
      {embodiment_json(R"({"name": "a", "min": "0", "max": 1})"), "joints[0].min: expected a number, got \"0\""},
      {embodiment_json(R"({"name": "a", "max": 1})"), "joints[0].min: missing"},
      {embodiment_json(R"({"name": "", "min": 0, "max": 1})"), "joints[0].name: expected a non-empty string"},
      {embodiment_json(R"({"name": "a", "min": 0, "max": 1, "max_acceleration": 0})"),
       "joints[0].max_acceleration: expected a positive number, got 0"},
      {embodiment_json(R"([1, 2])"), "joints[0]: expected a JSON object, got [1,2]"},
      {embodiment_json(""), "joints: expected a non-empty array of joints, got []"},
      {R"({"name": "arm", "units": "rad", "control_rate_hz": 10})", "joints: missing"},
      {"[]", "expected a JSON object"},
      {"{\"name\": ", "not valid JSON"},
  };
  for (size_t i = 0; i < cases.size(); ++i) {
    SCOPED_TRACE(cases[i].second);
    const std::string path = write_file("bad_" + std::to_string(i) + ".json", cases[i].first);
    const Error e = error_of([&] { load_embodiment_file(path); });
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    EXPECT_NE(std::string(e.what()).find(path + ": "), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(cases[i].second), std::string::npos) << e.what();
  }
}

TEST(Embodiment, MissingFilesAndUnknownPresets) {
  EXPECT_EQ(error_of([] { load_embodiment_file("/nonexistent/arm.json"); }).code(), ErrorCode::not_found);
  const Error unknown = error_of([] { load_embodiment_preset("franka2", kPresets); });
  EXPECT_EQ(unknown.code(), ErrorCode::not_found);
  EXPECT_NE(std::string(unknown.what()).find("'franka2' (presets: franka, quadcopter, so100, ur5)"),
            std::string::npos)
      << unknown.what();
  EXPECT_EQ(error_of([] { embodiment_presets("/nonexistent"); }).code(), ErrorCode::not_found);

  // A preset whose "name" is not its file's name.
  const fs::path dir = temp_dir() / "presets";
  fs::create_directories(dir);
  std::ofstream(dir / "arm2.json") << embodiment_json(kValidJoint);
  const Error e = error_of([&] { load_embodiment_preset("arm2", dir.string()); });
  EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
  EXPECT_NE(std::string(e.what()).find("arm2.json: name: expected 'arm2'"), std::string::npos) << e.what();
}

TEST(SafetyConfig, OverridesOnlyTheKindsOfLimitItGives) {
  const Embodiment so100 = load_embodiment_preset("so100", kPresets);
  const std::string path = write_file("safety.json", R"({
    "joint_limits": {
      "shoulder_pan": {"has_velocity_limits": true, "max_velocity": 40},
      "elbow_flex": {"has_position_limits": true, "min_position": -50, "max_position": 60},
      "wrist_roll": {"has_position_limits": false},
      "gripper": {"max_acceleration": 500}
    },
    "control_rate_hz": 25})");
  const SafetyConfig s = load_safety_config(path);
  EXPECT_EQ(s.control_rate_hz, 25);
  const std::vector<JointLimits> l = apply_safety_config(s, so100.joints, so100.limits);
  ASSERT_EQ(l.size(), 6u);
  // shoulder_pan: velocity replaced, position kept from the preset.
  EXPECT_EQ(l[0].max_velocity, 40);
  EXPECT_TRUE(l[0].has_position_limits);
  EXPECT_EQ(l[0].min_position, -100);
  // elbow_flex: tighter positions, the preset's velocity.
  EXPECT_EQ(l[2].min_position, -50);
  EXPECT_EQ(l[2].max_position, 60);
  EXPECT_EQ(l[2].max_velocity, 150);
  // wrist_roll: position limits turned off, velocity kept.
  EXPECT_FALSE(l[4].has_position_limits);
  EXPECT_TRUE(l[4].has_velocity_limits);
  // gripper: a value without its flag turns the limit on.
  EXPECT_TRUE(l[5].has_acceleration_limits);
  EXPECT_EQ(l[5].max_acceleration, 500);
  // Untouched joint.
  EXPECT_EQ(l[1].max_velocity, so100.limits[1].max_velocity);
  EXPECT_EQ(l[1].min_position, so100.limits[1].min_position);
}

TEST(SafetyConfig, WithoutEmbodimentMatchesGenericJointNames) {
  const std::string path = write_file("safety_generic.json", R"({"joint_limits": {
      "joint_1": {"has_position_limits": true, "min_position": -1.5, "max_position": 1.5,
                  "has_velocity_limits": true, "max_velocity": 2.0, "has_acceleration_limits": false,
                  "has_effort_limits": true, "max_effort": 150.0, "has_jerk_limits": false,
                  "has_deceleration_limits": false, "angle_wraparound": false}}})");
  const SafetyConfig s = load_safety_config(path);
  EXPECT_FALSE(s.control_rate_hz);
  const std::vector<JointLimits> l = apply_safety_config(s, {"joint_0", "joint_1", "joint_2"}, {});
  ASSERT_EQ(l.size(), 3u);
  EXPECT_FALSE(l[0].has_position_limits || l[0].has_velocity_limits || l[0].has_acceleration_limits);
  EXPECT_TRUE(l[1].has_position_limits);
  EXPECT_EQ(l[1].min_position, -1.5);
  EXPECT_EQ(l[1].max_velocity, 2.0);
  EXPECT_FALSE(l[1].has_acceleration_limits);

  const Error e = error_of([&] { apply_safety_config(s, {"joint_0"}, {}); });
  EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
  EXPECT_NE(std::string(e.what()).find(path + ": joint_limits.joint_1: no such joint (joints: joint_0)"),
            std::string::npos)
      << e.what();
}

TEST(SafetyConfig, EachKindOfBadFileNamesTheField) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {R"({"joint_limits": {"a": {"has_velocity_limits": true, "max_velocty": 2}}})",
       "joint_limits.a: unknown key 'max_velocty'"},
      {R"({"joint_limits": {"a": {"has_velocity_limits": true}}})",
       "joint_limits.a.max_velocity: missing (has_velocity_limits is true)"},
      {R"({"joint_limits": {"a": {"min_position": 1}}})",
       "joint_limits.a.max_position: missing (min_position is given)"},
      {R"({"joint_limits": {"a": {"min_position": 1, "max_position": 0}}})",
       "joint_limits.a.max_position: expected at least min_position (1), got 0"},
      {R"({"joint_limits": {"a": {"max_velocity": -2}}})",
       "joint_limits.a.max_velocity: expected a positive number, got -2"},
      {R"({"joint_limits": {"a": {"has_velocity_limits": "yes", "max_velocity": 2}}})",
       "joint_limits.a.has_velocity_limits: expected true or false, got \"yes\""},
      {R"({"joint_limits": {"a": {"has_jerk_limits": true, "max_jerk": 100}}})",
       "joint_limits.a.has_jerk_limits: the action guard enforces position, velocity and acceleration limits only"},
      {R"({"joint_limits": {"a": {"max_deceleration": 3}}})", "joint_limits.a.has_deceleration_limits: the action"},
      {R"({"joint_limits": {"a": {"angle_wraparound": true}}})", "joint_limits.a.angle_wraparound: not supported"},
      {R"({"joint_limits": {"a": 3}})", "joint_limits.a: expected a JSON object, got 3"},
      {R"({"joint_limits": []})", "joint_limits: expected an object of joints, got []"},
      {R"({"joints": {}})", "unknown key 'joints'"},
      {R"({"control_rate_hz": 30})", "joint_limits: missing"},
      {R"({"joint_limits": {}, "control_rate_hz": -30})", "control_rate_hz: expected a positive number, got -30"},
  };
  for (size_t i = 0; i < cases.size(); ++i) {
    SCOPED_TRACE(cases[i].second);
    const std::string path = write_file("bad_safety_" + std::to_string(i) + ".json", cases[i].first);
    const Error e = error_of([&] { load_safety_config(path); });
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    EXPECT_NE(std::string(e.what()).find(path + ": " + cases[i].second), std::string::npos) << e.what();
  }
  EXPECT_EQ(error_of([] { load_safety_config("/nonexistent/safety.json"); }).code(), ErrorCode::not_found);
}
