// Embodiment and safety-config files: strict parsing (every field checked, unknown keys rejected) with errors that
// name the file and the field.
#include "policy/embodiment.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <initializer_list>

#include "core/json_util.h"

namespace tether::policy {

namespace fs = std::filesystem;

namespace {

[[noreturn]] void fail(const std::string& at, const std::string& message) {
  throw Error(ErrorCode::invalid_argument, at + ": " + message);
}

// One JSON object of a config file: typed access to its fields, and no key outside `allowed`.
class Fields {
 public:
  Fields(const Json& j, std::string file, std::string path, std::initializer_list<const char*> allowed)
      : j_(j), file_(std::move(file)), path_(std::move(path)) {
    const std::string here = path_.empty() ? file_ : file_ + ": " + path_;
    if (!j.is_object()) fail(here, "expected a JSON object, got " + j.dump());
    for (auto it = j.begin(); it != j.end(); ++it) {
      if (std::none_of(allowed.begin(), allowed.end(), [&](const char* k) { return it.key() == k; })) {
        std::string keys;
        for (const char* k : allowed) keys += std::string(keys.empty() ? "" : ", ") + k;
        fail(here, "unknown key '" + it.key() + "' (expected: " + keys + ")");
      }
    }
  }

  // "file: path.key", the place an error about `key` names.
  std::string at(const std::string& key) const { return file_ + ": " + (path_.empty() ? key : path_ + "." + key); }
  const Json* find(const std::string& key) const {
    auto it = j_.find(key);
    return it == j_.end() ? nullptr : &*it;
  }
  std::optional<double> number(const std::string& key, bool positive) const {
    const Json* v = find(key);
    if (!v) return std::nullopt;
    const char* expected = positive ? "expected a positive number" : "expected a number";
    if (!v->is_number()) fail(at(key), std::string(expected) + ", got " + v->dump());
    const double x = v->get<double>();
    if (!std::isfinite(x) || (positive && !(x > 0))) fail(at(key), std::string(expected) + ", got " + v->dump());
    return x;
  }
  double required_number(const std::string& key, bool positive) const {
    if (auto x = number(key, positive)) return *x;
    fail(at(key), "missing");
  }
  std::optional<bool> boolean(const std::string& key) const {
    const Json* v = find(key);
    if (!v) return std::nullopt;
    if (!v->is_boolean()) fail(at(key), "expected true or false, got " + v->dump());
    return v->get<bool>();
  }
  std::optional<std::string> text(const std::string& key, bool non_empty) const {
    const Json* v = find(key);
    if (!v) return std::nullopt;
    if (!v->is_string() || (non_empty && v->get<std::string>().empty()))
      fail(at(key), std::string(non_empty ? "expected a non-empty string" : "expected a string") + ", got " +
                        v->dump());
    return v->get<std::string>();
  }
  std::string required_text(const std::string& key) const {
    if (auto s = text(key, true)) return *s;
    fail(at(key), "missing");
  }

 private:
  const Json& j_;
  std::string file_, path_;
};

// A number as the file wrote it (1, not 1.0), or as computed when it came from a default.
std::string shown(const Fields& f, const char* key, double x) {
  const Json* j = f.find(key);
  return j ? j->dump() : Json(x).dump();
}

void check_order(const Fields& f, const char* lo_key, double lo, const char* hi_key, double hi) {
  if (lo > hi)
    fail(f.at(hi_key), std::string("expected at least ") + lo_key + " (" + shown(f, lo_key, lo) + "), got " +
                           shown(f, hi_key, hi));
}

// Malformed JSON is a bad file like any other: invalid_argument, whatever is wrong with it.
Json read_config(const std::string& path) {
  try {
    return read_json_file(path);
  } catch (const Error& e) {
    if (e.code() == ErrorCode::format) throw Error(ErrorCode::invalid_argument, e.what());
    throw;
  }
}

Embodiment parse_embodiment(const Json& j, const std::string& file) {
  Fields top(j, file, "", {"name", "description", "units", "control_rate_hz", "source", "joints"});
  Embodiment e;
  e.name = top.required_text("name");
  e.description = top.text("description", false).value_or("");
  e.units = top.required_text("units");
  e.source = top.text("source", false).value_or("");
  e.control_rate_hz = top.required_number("control_rate_hz", true);
  const Json* joints = top.find("joints");
  if (!joints) fail(top.at("joints"), "missing");
  if (!joints->is_array() || joints->empty())
    fail(top.at("joints"), "expected a non-empty array of joints, got " + joints->dump());
  std::map<std::string, size_t> seen;
  for (size_t i = 0; i < joints->size(); ++i) {
    Fields f((*joints)[i], file, "joints[" + std::to_string(i) + "]",
             {"name", "min", "max", "min_position", "max_position", "max_velocity", "max_acceleration"});
    const std::string name = f.required_text("name");
    if (auto [it, fresh] = seen.emplace(name, i); !fresh)
      fail(f.at("name"), "duplicate joint name '" + name + "' (also joints[" + std::to_string(it->second) + "])");
    const double lo = f.required_number("min", false), hi = f.required_number("max", false);
    check_order(f, "min", lo, "max", hi);
    JointLimits l;
    const auto min_pos = f.number("min_position", false), max_pos = f.number("max_position", false);
    if (min_pos.has_value() != max_pos.has_value())
      fail(f.at(min_pos ? "max_position" : "min_position"),
           std::string("missing (") + (min_pos ? "min_position" : "max_position") + " is given)");
    l.has_position_limits = true;
    l.min_position = min_pos.value_or(lo);
    l.max_position = max_pos.value_or(hi);
    check_order(f, "min_position", l.min_position, "max_position", l.max_position);
    if (auto v = f.number("max_velocity", true)) {
      l.has_velocity_limits = true;
      l.max_velocity = *v;
    }
    if (auto a = f.number("max_acceleration", true)) {
      l.has_acceleration_limits = true;
      l.max_acceleration = *a;
    }
    e.joints.push_back(name);
    e.range_min.push_back(lo);
    e.range_max.push_back(hi);
    e.limits.push_back(l);
  }
  return e;
}

// One kind of limit in a safety entry: the has_* flag and its value keys. Returns whether the entry sets the kind
// and, if so, whether the limit is on. A value without its flag turns the limit on.
struct KindSetting {
  bool given = false, on = false;
};
KindSetting kind_setting(const Fields& f, const char* flag, std::initializer_list<const char*> value_keys) {
  const std::optional<bool> has = f.boolean(flag);
  const char* given_value = nullptr;
  for (const char* k : value_keys)
    if (!given_value && f.find(k)) given_value = k;
  if (has == false) return {true, false};
  if (!has && !given_value) return {false, false};
  const std::string reason = has ? std::string(flag) + " is true" : std::string(given_value) + " is given";
  for (const char* k : value_keys)
    if (!f.find(k)) fail(f.at(k), "missing (" + reason + ")");
  return {true, true};
}

}  // namespace

void Embodiment::map_normalized_to_range(float* actions, int64_t rows) const {
  const size_t dim = joints.size();
  for (int64_t r = 0; r < rows; ++r)
    for (size_t j = 0; j < dim; ++j) {
      float& a = actions[size_t(r) * dim + j];
      a = float(range_min[j] + (double(a) + 1.0) * 0.5 * (range_max[j] - range_min[j]));
    }
}

void Embodiment::map_range_to_normalized(float* actions, int64_t rows) const {
  const size_t dim = joints.size();
  for (int64_t r = 0; r < rows; ++r)
    for (size_t j = 0; j < dim; ++j) {
      float& a = actions[size_t(r) * dim + j];
      const double span = range_max[j] - range_min[j];
      a = span > 0 ? float((double(a) - range_min[j]) / span * 2.0 - 1.0) : 0.0f;
    }
}

Embodiment load_embodiment_file(const std::string& path) { return parse_embodiment(read_config(path), path); }

std::vector<std::string> embodiment_presets(const std::string& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) throw Error(ErrorCode::not_found, dir + ": embodiment preset directory not found");
  std::vector<std::string> names;
  for (const auto& entry : fs::directory_iterator(dir))
    if (entry.is_regular_file() && entry.path().extension() == ".json") names.push_back(entry.path().stem().string());
  std::sort(names.begin(), names.end());
  return names;
}

Embodiment load_embodiment_preset(const std::string& name, const std::string& dir) {
  const std::vector<std::string> names = embodiment_presets(dir);
  if (std::find(names.begin(), names.end(), name) == names.end()) {
    std::string list;
    for (const auto& n : names) list += (list.empty() ? "" : ", ") + n;
    throw Error(ErrorCode::not_found, "unknown embodiment '" + name + "' (presets: " + list + ")");
  }
  const std::string path = (fs::path(dir) / (name + ".json")).string();
  Embodiment e = load_embodiment_file(path);
  if (e.name != name) fail(path + ": name", "expected '" + name + "' (the file's name), got '" + e.name + "'");
  return e;
}

SafetyConfig load_safety_config(const std::string& path) {
  const Json j = read_config(path);
  Fields top(j, path, "", {"joint_limits", "control_rate_hz"});
  SafetyConfig s;
  s.path = path;
  s.control_rate_hz = top.number("control_rate_hz", true);
  const Json* joints = top.find("joint_limits");
  if (!joints) fail(top.at("joint_limits"), "missing");
  if (!joints->is_object()) fail(top.at("joint_limits"), "expected an object of joints, got " + joints->dump());
  for (auto it = joints->begin(); it != joints->end(); ++it) {
    Fields f(it.value(), path, "joint_limits." + it.key(),
             {"has_position_limits", "min_position", "max_position", "has_velocity_limits", "max_velocity",
              "has_acceleration_limits", "max_acceleration", "has_deceleration_limits", "max_deceleration",
              "has_jerk_limits", "max_jerk", "has_effort_limits", "max_effort", "angle_wraparound"});
    JointLimits l;
    SafetyConfig::Given g;
    const auto min_pos = f.number("min_position", false), max_pos = f.number("max_position", false);
    const auto max_vel = f.number("max_velocity", true), max_acc = f.number("max_acceleration", true);
    for (const char* k : {"max_deceleration", "max_jerk", "max_effort"}) f.number(k, true);
    const KindSetting pos = kind_setting(f, "has_position_limits", {"min_position", "max_position"});
    const KindSetting vel = kind_setting(f, "has_velocity_limits", {"max_velocity"});
    const KindSetting acc = kind_setting(f, "has_acceleration_limits", {"max_acceleration"});
    kind_setting(f, "has_effort_limits", {"max_effort"});
    for (auto [flag, value] : {std::pair{"has_deceleration_limits", "max_deceleration"},
                               std::pair{"has_jerk_limits", "max_jerk"}})
      if (kind_setting(f, flag, {value}).on)
        fail(f.at(flag), "the action guard enforces position, velocity and acceleration limits only; set it to "
                         "false or remove the limit");
    if (f.boolean("angle_wraparound") == true)
      fail(f.at("angle_wraparound"), "not supported: the action guard clamps positions to [min_position, "
                                     "max_position]; set it to false");
    g = {pos.given, vel.given, acc.given};
    l.has_position_limits = pos.on;
    if (pos.on) {
      l.min_position = *min_pos;
      l.max_position = *max_pos;
      check_order(f, "min_position", l.min_position, "max_position", l.max_position);
    }
    l.has_velocity_limits = vel.on;
    l.max_velocity = vel.on ? *max_vel : 0;
    l.has_acceleration_limits = acc.on;
    l.max_acceleration = acc.on ? *max_acc : 0;
    s.joints[it.key()] = l;
    s.given[it.key()] = g;
  }
  return s;
}

std::vector<JointLimits> apply_safety_config(const SafetyConfig& safety, const std::vector<std::string>& joint_names,
                                             std::vector<JointLimits> base) {
  if (base.empty()) base.resize(joint_names.size());
  if (base.size() != joint_names.size())
    throw Error(ErrorCode::internal, "apply_safety_config: " + std::to_string(base.size()) + " limits for " +
                                         std::to_string(joint_names.size()) + " joints");
  for (const auto& [name, l] : safety.joints) {
    auto it = std::find(joint_names.begin(), joint_names.end(), name);
    if (it == joint_names.end()) {
      std::string list;
      for (const auto& n : joint_names) list += (list.empty() ? "" : ", ") + n;
      fail(safety.path + ": joint_limits." + name, "no such joint (joints: " + list + ")");
    }
    JointLimits& out = base[size_t(it - joint_names.begin())];
    auto g = safety.given.find(name);
    const SafetyConfig::Given given = g == safety.given.end() ? SafetyConfig::Given{true, true, true} : g->second;
    if (given.position) {
      out.has_position_limits = l.has_position_limits;
      out.min_position = l.min_position;
      out.max_position = l.max_position;
    }
    if (given.velocity) {
      out.has_velocity_limits = l.has_velocity_limits;
      out.max_velocity = l.max_velocity;
    }
    if (given.acceleration) {
      out.has_acceleration_limits = l.has_acceleration_limits;
      out.max_acceleration = l.max_acceleration;
    }
  }
  return base;
}

}  // namespace tether::policy
