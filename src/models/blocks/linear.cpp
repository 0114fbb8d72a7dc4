// Checked loading of linear layers into a backend (see linear.h).
#include "models/blocks/linear.h"

namespace tether::models {

std::unique_ptr<backend::LinearWeights> load_linear(backend::Backend& be, Weights& w, const std::string& name, int64_t n,
                                                    int64_t k, bool bias, cpu::Precision precision) {
  return load_stacked_linear(be, w, {{name, n}}, k, bias, precision);
}

std::unique_ptr<backend::LinearWeights> load_stacked_linear(backend::Backend& be, Weights& w,
                                                            const std::vector<std::pair<std::string, int64_t>>& parts,
                                                            int64_t k, bool bias, cpu::Precision precision) {
  std::vector<std::pair<std::string, Shape>> weights, biases;
  int64_t n = 0;
  for (const auto& [name, rows] : parts) {
    weights.push_back({name + ".weight", {rows, k}});
    biases.push_back({name + ".bias", {rows}});
    n += rows;
  }
  const std::vector<float> wt = w.stacked(weights);
  const std::vector<float> b = bias ? w.stacked(biases) : std::vector<float>{};
  return be.pack_linear(wt.data(), n, k, bias ? b.data() : nullptr, precision);
}

}  // namespace tether::models
