// A model family's contract with the rest of Tether. policy/, runtime/, serve/ and cli/ never name a family: they
// ask the descriptor (or the ModelSpec its model fills) how a checkpoint is recognised, which files hold its
// weights, how its normaliser is read, what its cameras and stages are and what an export carries.
// Adding a family is one file (or folder) under src/models/ that defines a FamilyDescriptor, plus one line in
// registry.cpp; docs/adding-a-model.md walks through it.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "core/json_util.h"
#include "models/model.h"
#include "models/normalization.h"
#include "models/weights.h"

namespace tether::models {

// What recognition sees: the directory and its config.json (null when there is none), read once for all families.
struct CheckpointProbe {
  std::filesystem::path dir;
  Json config;  // null: no config.json
};

enum class TokenizerKind { byte_level_bpe, sentencepiece };
const char* tokenizer_kind_name(TokenizerKind k);

// What `tether export` writes for a checkpoint, besides the weights (converted to the export precision) and the
// receipt. Paths are relative to the checkpoint directory (`copy`) or absolute (`bundles[].from`).
struct ExportPlan {
  std::vector<std::string> copy;  // files copied unchanged (processor pipelines, their statistics, ...)
  struct Bundle {
    std::filesystem::path from;      // a directory outside the checkpoint the model needs (a VLM backbone)
    std::string to;                  // the sub-directory of the export it is copied into
    std::vector<std::string> files;  // the files copied, relative to `from`
  };
  std::vector<Bundle> bundles;
  Json config;  // config.json as the export writes it (bundle references rewritten to their new place)
  // Files the export writes from these contents instead of copying them (GR00T: the sidecars narrowed to the one
  // embodiment exported).
  std::vector<std::pair<std::string, Json>> written;
  // Tensors of the weight files kept in their stored dtype whatever the export precision (statistics a legacy
  // layout keeps among the weights).
  std::vector<std::string> keep_dtype;
};

struct FamilyDescriptor {
  std::string name;         // "smolvla": ModelSpec::family, /config, traces
  std::string summary;      // one line: what the family is
  std::string recognition;  // one line: what makes a checkpoint this family's (errors list it)
  bool (*recognises)(const CheckpointProbe&) = nullptr;

  TokenizerKind tokenizer = TokenizerKind::byte_level_bpe;
  // The model's timed stages in order (ModelSpec::stages, StageTimings); the first one is where callers add their
  // own input handling (parsing, normalisation) when they report a stage breakdown.
  std::vector<std::string> stages;
  // How a camera the request leaves out is handled, one sentence (ModelSpec::missing_camera_rule).
  std::string missing_camera_rule;

  // The weight files of a checkpoint directory, relative names (an index and its shards, or one file); empty
  // when there are none.
  std::vector<std::string> (*weight_files)(const std::filesystem::path& dir) = nullptr;
  // Opens the weights (one file or the shards of an index).
  TensorStore (*open_weights)(const std::filesystem::path& dir) = nullptr;
  // Reads the normaliser; may take tensors out of `weights` (statistics a legacy layout kept there). `options` says
  // which embodiment is served, for checkpoints that hold statistics per embodiment.
  Normalization (*load_normalization)(const std::filesystem::path& dir, const Json& config, TensorStore& weights,
                                      const LoadOptions& options) = nullptr;
  // Builds the model from the opened weights.
  std::unique_ptr<Model> (*load)(const std::filesystem::path& dir, const Json& config, TensorStore weights,
                                 const LoadOptions& options) = nullptr;
  // The files an export carries and its rewritten config.json; options.embodiment: the one embodiment exported, for
  // checkpoints trained on several (empty: all of them).
  ExportPlan (*export_plan)(const std::filesystem::path& dir, const Json& config, const LoadOptions& options) = nullptr;
  // Whether the loaded model keeps its own copy of a tensor (converted to the compute precision); false for tensors
  // it never reads or reads a row at a time from the mapped file (token embeddings). Null: every tensor. The doctor's
  // memory estimate counts these.
  bool (*keeps_copy)(const std::string& tensor) = nullptr;
};

// Every family this build knows, in registry order.
const std::vector<const FamilyDescriptor*>& families();
std::vector<std::string> model_families();
const FamilyDescriptor* find_family(const std::string& name);  // null when unknown

// The family that recognises `dir`; throws unsupported naming the checkpoint's identity and every known family
// with what it recognises (not_found when there is no config.json).
const FamilyDescriptor& recognise(const std::filesystem::path& dir);
const FamilyDescriptor& recognise(const CheckpointProbe& probe);
CheckpointProbe probe_checkpoint(const std::filesystem::path& dir);

// A checkpoint loaded through its family: the model, its normaliser and what the user should know.
struct LoadedCheckpoint {
  const FamilyDescriptor* family = nullptr;
  Json config;
  std::vector<std::string> weight_files;  // relative to the directory
  std::unique_ptr<Model> model;
  Normalization normalization;
};
LoadedCheckpoint load_checkpoint(const std::filesystem::path& dir, const LoadOptions& options = {});

// sha256 of the weights: of the file itself for one file ("sha256:<hex>"); for shards, of the lines
// "<sha256>  <file>\n" of the index and each shard in order (what sha256sum prints), so that it changes when any of
// them does.
std::string weights_hash(const std::filesystem::path& dir, const std::vector<std::string>& weight_files);

}  // namespace tether::models
