// pi0 and pi0.5 (lerobot's ports of openpi's PI0Pytorch): PaliGemma (SigLIP + Gemma 2B) as the prefix encoder, a
// Gemma 300M action expert attending jointly to the prefix K/V, and a flow-matching Euler sampler. pi0.5 differs in
// its adaptive RMSNorms conditioned on the time and a state written into the prompt.
#pragma once

#include <filesystem>
#include <memory>

#include "models/family.h"

namespace tether::models {

// The families' descriptors (pi0_family.cpp): lerobot types "pi0" and "pi05".
const FamilyDescriptor& pi0_family();
const FamilyDescriptor& pi05_family();

// The models from a checkpoint directory and its opened weights (pi0.cpp).
std::unique_ptr<Model> load_pi0(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                TensorStore weights, const LoadOptions& options);
std::unique_ptr<Model> load_pi05(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                 TensorStore weights, const LoadOptions& options);

}  // namespace tether::models
