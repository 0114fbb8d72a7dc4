// SmolVLA (lerobot): SmolVLM vision tower + truncated SmolLM2 decoder as the prefix encoder, a narrower Llama
// "action expert" interleaving self- and cross-attention to the prefix K/V, and a flow-matching Euler sampler.
#pragma once

#include <filesystem>
#include <memory>

#include "models/family.h"

namespace tether::models {

// The family's descriptor (smolvla_family.cpp): lerobot type "smolvla".
const FamilyDescriptor& smolvla_family();

// The model from a checkpoint directory and its opened weights (smolvla.cpp).
std::unique_ptr<Model> load_smolvla(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                    TensorStore weights, const LoadOptions& options);

}  // namespace tether::models
