// Model family registry: adding a family is one file plus one line here.
#include <cmath>
#include <random>

#include "models/model.h"
#include "models/smolvla.h"

namespace tether::models {

namespace {
struct Family {
  const char* type;
  std::unique_ptr<Model> (*load)(const std::string& dir, const Json& config, const LoadOptions& options);
};
constexpr Family kFamilies[] = {
    {"smolvla", &load_smolvla},
};
}  // namespace

std::unique_ptr<Model> load_model(const std::string& dir, const Json& config, const LoadOptions& options) {
  const std::string type = json_get<std::string>(config, "type", dir + "/config.json");
  for (const auto& f : kFamilies)
    if (type == f.type) return f.load(dir, config, options);
  std::string known;
  for (const auto& f : kFamilies) known += std::string(known.empty() ? "" : ", ") + f.type;
  throw Error(ErrorCode::unsupported, dir + "/config.json: model type '" + type + "' is not supported (supported: " +
                                          known + ")");
}

std::vector<std::string> model_families() {
  std::vector<std::string> out;
  for (const auto& f : kFamilies) out.push_back(f.type);
  return out;
}

void seeded_normal(uint64_t seed, float* out, int64_t n) {
  std::mt19937_64 gen(seed);
  auto uniform = [&] { return (double(gen() >> 11) + 0.5) * 0x1.0p-53; };  // in (0, 1), never 0
  constexpr double two_pi = 6.283185307179586476925286766559;
  for (int64_t i = 0; i < n; i += 2) {
    const double r = std::sqrt(-2.0 * std::log(uniform()));
    const double theta = two_pi * uniform();
    out[i] = float(r * std::cos(theta));
    if (i + 1 < n) out[i + 1] = float(r * std::sin(theta));
  }
}

}  // namespace tether::models
