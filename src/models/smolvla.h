// SmolVLA (lerobot): SmolVLM vision tower + truncated SmolLM2 decoder as the prefix encoder, a narrower Llama
// "action expert" interleaving self- and cross-attention to the prefix K/V, and a flow-matching Euler sampler.
#pragma once

#include <memory>
#include <string>

#include "models/model.h"

namespace tether::models {

std::unique_ptr<Model> load_smolvla(const std::string& checkpoint_dir, const Json& policy_config,
                                    const LoadOptions& options);

}  // namespace tether::models
