// Loading nn.Linear layers from a checkpoint into a backend: names, shapes and dtypes checked, q/k/v or gate/up
// stacked into one matrix so one product computes them all.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "backend/backend.h"
#include "models/weights.h"

namespace tether::models {

// `<name>.weight` [n, k] (and `<name>.bias` [n] when `bias`).
std::unique_ptr<backend::LinearWeights> load_linear(backend::Backend& be, Weights& w, const std::string& name, int64_t n,
                                                    int64_t k, bool bias, cpu::Precision precision);
// Several layers with the same input, stacked by output: parts are (name, n_i), the result has sum(n_i) outputs.
std::unique_ptr<backend::LinearWeights> load_stacked_linear(backend::Backend& be, Weights& w,
                                                            const std::vector<std::pair<std::string, int64_t>>& parts,
                                                            int64_t k, bool bias, cpu::Precision precision);
// 2 * rows * n * k: the multiply-adds of one forward over `rows` inputs.
inline double linear_flops(const backend::LinearWeights& l, int64_t rows) {
  return 2.0 * double(rows) * double(l.out_features()) * double(l.in_features());
}

}  // namespace tether::models
