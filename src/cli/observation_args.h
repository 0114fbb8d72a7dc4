// Flags shared by the verbs that build an observation from files (predict, bench).
#pragma once

#include <CLI/CLI.hpp>
#include <string>
#include <vector>

#include "policy/policy.h"

namespace tether::cli {

struct ObservationArgs {
  std::vector<std::string> images;  // CAMERA=FILE
  std::string state;                // comma-separated
  std::string instruction;
  std::string noise_file;
  uint64_t seed = 0;

  // `required`: predict needs real inputs; bench falls back to synthetic ones.
  void add_to(CLI::App* sub, bool required);
  // Builds the observation; with no images/state given, uses a mid-grey frame per camera and a zero state.
  policy::Observation build(const policy::Policy& policy) const;
};

std::vector<float> parse_floats(const std::string& text, const std::string& flag);

// --precision fp32|bf16, shared by the verbs that load a model.
void add_precision_flag(CLI::App* sub, std::string& value);
// --embodiment-tag TAG, for checkpoints trained on several embodiments (GR00T); empty: the checkpoint's only one.
void add_embodiment_tag_flag(CLI::App* sub, std::string& value);
// --backend cpu|cuda|auto (see docs/backends.md); `value` keeps its default (cpu for most verbs, auto for go).
void add_backend_flag(CLI::App* sub, std::string& value);
// Throws Error(invalid_argument) with the one-line reason (exit code 2) when the backend asked for cannot run here.
models::LoadOptions load_options(const std::string& precision, const std::string& embodiment_tag = "",
                                 const std::string& backend = "cpu");
// What inference actually ran in: "cpu-fp32", "cpu-bf16" (native bf16 GEMM), "cpu-bf16-weights" /
// "cpu-fp16-weights" (half-size weights widened to fp32 in the kernel).
std::string inference_mode(const models::ModelSpec& spec);

}  // namespace tether::cli
