// Small checkpoints of random float32 tensors for the block tests: tensors kept for the plain references, written
// as a safetensors file for the blocks to load.
#pragma once

#include <filesystem>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "core/safetensors.h"
#include "core/tensor.h"
#include "scratch_dir.h"

namespace tether::test_util {

inline std::vector<float> random_vec(int64_t n, uint32_t seed, float scale = 0.5f) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(-scale, scale);
  std::vector<float> v(static_cast<std::size_t>(n));
  for (auto& x : v) x = dist(gen);
  return v;
}

struct RandomCheckpoint {
  std::map<std::string, std::vector<float>> tensors;
  std::map<std::string, Shape> shapes;
  void add(const std::string& name, Shape shape, uint32_t seed) {
    tensors[name] = random_vec(shape_numel(shape), seed);
    shapes[name] = std::move(shape);
  }
  const std::vector<float>& operator[](const std::string& name) const { return tensors.at(name); }
  // Writes every tensor to a temporary safetensors file named after `tag`; returns its path.
  std::string write(const std::string& tag) const {
    std::map<std::string, Tensor> out;
    for (const auto& [name, values] : tensors) out[name] = Tensor{DType::f32, shapes.at(name), values.data(), nullptr};
    const auto path = tether::testing::scratch_dir() / (tag + ".safetensors");
    write_safetensors(path.string(), out);
    return path.string();
  }
};

}  // namespace tether::test_util
