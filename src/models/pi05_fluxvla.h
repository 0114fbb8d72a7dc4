// pi0.5 as FluxVLA trains and saves it (limxdynamics/FluxVLA, PI05FlowMatching): its run directory read as is
// (config.json, checkpoints/step-*.safetensors, dataset_statistics.json, tokenizer/tokenizer.model), the weights
// renamed to lerobot's PI05Policy names, and the network built by the pi0.5 model with FluxVLA's preprocessing.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include "models/family.h"
#include "models/pi0.h"

namespace tether::models {

const FamilyDescriptor& pi05_fluxvla_family();

// The weight file a run directory is read from: checkpoints/step-<N>-....safetensors with the highest N (relative
// to `dir`); nullopt when there is none. Throws format when two files claim the highest step.
std::optional<std::string> fluxvla_weights_file(const std::filesystem::path& dir);

// A FluxVLA parameter's name in lerobot's PI05Policy (prefix renames, nothing else changes); nullopt for the
// expert's token embedding, which FluxVLA keeps but never uses. Throws format naming `where` for a name that is not a
// PI05FlowMatching parameter.
std::optional<std::string> fluxvla_to_lerobot_name(const std::string& name, const std::string& where);

// What the loader derives from FluxVLA's config.json and dataset_statistics.json: lerobot PI05Config fields for the
// pi0.5 model, and how it is fed.
struct FluxvlaModel {
  Json policy_config;
  PiZeroOptions options;
};
FluxvlaModel read_fluxvla_model(const std::filesystem::path& dir, const Json& config);

}  // namespace tether::models
