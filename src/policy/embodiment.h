// Robot embodiments (action order, action range, joint limits, control rate) from preset or custom JSON files, and
// the safety config that overrides joint limits in the shape of ros2_control's joint_limits parameters.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace tether::policy {

// The fields of ros2_control's joint_limits::JointLimits that the action guard enforces.
struct JointLimits {
  bool has_position_limits = false;
  double min_position = 0, max_position = 0;
  bool has_velocity_limits = false;
  double max_velocity = 0;
  bool has_acceleration_limits = false;
  double max_acceleration = 0;
};

// File format (every key checked, unknown keys rejected):
//   {"name": "...", "description": "...", "units": "rad", "control_rate_hz": 15, "source": "...",
//    "joints": [{"name": "j1", "min": -1, "max": 1, "min_position": -1, "max_position": 1,
//                "max_velocity": 2.0, "max_acceleration": 15.0}, ...]}
// description and source are optional; per joint, min/max (the action range) are required, min_position and
// max_position default to the action range, max_velocity and max_acceleration are optional (no limit when absent).
struct Embodiment {
  std::string name, description, units, source;
  double control_rate_hz = 0;
  std::vector<std::string> joints;           // action order
  std::vector<double> range_min, range_max;  // the action range per joint
  std::vector<JointLimits> limits;

  // Model output normalised to [-1, 1] (a checkpoint without action stats) -> the action range, linearly:
  // -1 -> min, 1 -> max. `actions` holds rows x joints.size() values; out-of-range and non-finite values map as the
  // formula says and are left to the action guard.
  void map_normalized_to_range(float* actions, int64_t rows) const;
  // Its inverse (min -> -1, max -> 1), for actions in robot units handed back to the model (RTC's leftover).
  void map_range_to_normalized(float* actions, int64_t rows) const;
};

// Errors: a missing file -> not_found; anything wrong in it -> invalid_argument naming the file and the field,
// e.g. "so100.json: joints[2].max_velocity: expected a positive number, got -1".
Embodiment load_embodiment_file(const std::string& path);
// dir/<name>.json; a name without a file there -> not_found listing the presets. The file's "name" must be `name`.
Embodiment load_embodiment_preset(const std::string& name, const std::string& dir);
// The preset names in `dir` (the *.json files' stems), sorted.
std::vector<std::string> embodiment_presets(const std::string& dir);

// --safety-config: JSON in the shape of ros2_control's joint limits parameters,
//   {"joint_limits": {"shoulder_pan": {"has_position_limits": true, "min_position": -1.5, "max_position": 1.5,
//                                      "has_velocity_limits": true, "max_velocity": 2.0,
//                                      "has_acceleration_limits": false}, ...},
//    "control_rate_hz": 30}
// A kind of limit (position, velocity, acceleration) is set for a joint when its has_*_limits flag or its values are
// given: a value without its flag turns the limit on, a false flag turns it off. Kinds a joint's entry does not
// mention keep the embodiment's limit, as ros2_control's parameters override a URDF's limits. ros2_control's effort
// fields are accepted and ignored (actions carry no effort); jerk and deceleration limits and angle_wraparound are
// accepted only when off, since the guard cannot honour them. Unknown keys are errors: a typo must not pass silently.
struct SafetyConfig {
  struct Given {
    bool position = false, velocity = false, acceleration = false;
  };
  std::string path;  // for error messages
  std::map<std::string, JointLimits> joints;
  std::map<std::string, Given> given;  // which kinds each joint's entry sets
  std::optional<double> control_rate_hz;
};
SafetyConfig load_safety_config(const std::string& path);

// The limits of `joint_names` after `safety`'s overrides. `base` holds each joint's limits before them (the
// embodiment's) or is empty when there are none (the caller then passes "joint_0", "joint_1", ... as names). A joint
// the config names that is not in `joint_names` is an invalid_argument naming it. The config's control_rate_hz is
// the caller's to apply.
std::vector<JointLimits> apply_safety_config(const SafetyConfig& safety, const std::vector<std::string>& joint_names,
                                             std::vector<JointLimits> base);

}  // namespace tether::policy
