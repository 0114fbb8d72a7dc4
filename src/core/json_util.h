// Reading JSON config files with errors that name the file and the field at fault.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

#include "core/error.h"

namespace tether {

// Ordered: lerobot configs carry meaning in key order (the camera order of input_features).
using Json = nlohmann::ordered_json;
// Unordered, for large files where key order means nothing (a tokenizer's 50k-entry vocabulary): parsing into
// an ordered map is quadratic in the number of keys.
using JsonMap = nlohmann::json;

template <typename J = Json>
J read_json_file(const std::string& path);

// `where` names the file (and object path) for the error message, e.g. "ckpt/config.json".
template <typename T, typename J>
T json_get(const J& j, const std::string& key, const std::string& where) {
  auto it = j.find(key);
  if (it == j.end() || it->is_null()) throw Error(ErrorCode::not_found, where + ": missing field '" + key + "'");
  try {
    return it->template get<T>();
  } catch (const nlohmann::json::exception&) {
    throw Error(ErrorCode::format, where + ": field '" + key + "' has the wrong type (" + it->dump() + ")");
  }
}

template <typename T, typename J>
T json_get_or(const J& j, const std::string& key, T fallback, const std::string& where) {
  auto it = j.find(key);
  if (it == j.end() || it->is_null()) return fallback;
  return json_get<T>(j, key, where);
}

}  // namespace tether
