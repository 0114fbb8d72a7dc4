// Locating a policy's backbone files (its VLM's config.json and tokenizer), which LeRobot checkpoints name by Hugging
// Face id rather than ship.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

namespace tether::models {

// The directory holding `name`'s config.json: `name` relative to the checkpoint directory, an absolute path, or the
// snapshot of Hugging Face repo `name` in the local hub cache (tether::hf_hub_cache(), refs/main). Throws not_found naming every place looked at.
// `named_by` says where the name came from, for the error.
std::filesystem::path find_backbone_dir(const std::filesystem::path& checkpoint_dir, const std::string& name,
                                        const std::string& named_by = "vlm_model_name in config.json");

// Whether a family built on a VLM keeps its own copy of `tensor` (FamilyDescriptor::keeps_copy): not the lm_head (never
// used), the token embeddings (read a row at a time from the file) or the text model's final norm (never used).
bool vlm_keeps_copy(const std::string& tensor);

// The backbone files a deployment needs (architecture, tokenizer, processor settings), those present in `dir`.
std::vector<std::string> backbone_files(const std::filesystem::path& dir);

}  // namespace tether::models
