// pi0 and pi0.5 (lerobot's ports of openpi's PI0Pytorch): PaliGemma (SigLIP + Gemma 2B) as the prefix encoder, a
// Gemma 300M action expert attending jointly to the prefix K/V, and a flow-matching Euler sampler. pi0.5 differs in
// its adaptive RMSNorms conditioned on the time and a state written into the prompt.
#pragma once

#include <array>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "models/family.h"
#include "text/tokenizer.h"

namespace tether::models {

// The families' descriptors (pi0_family.cpp): lerobot types "pi0" and "pi05".
const FamilyDescriptor& pi0_family();
const FamilyDescriptor& pi05_family();

// How the same network is fed when a checkpoint was trained outside lerobot (FluxVLA's pi0.5). The defaults are
// lerobot's, bit for bit; every field only changes what it names.
struct PiZeroOptions {
  const FamilyDescriptor* family = nullptr;  // ModelSpec's family, stages and camera rule; null: pi0 / pi05
  // Images. lerobot: x / 255, resize-with-pad to the resolution, then [-1, 1]. mean_std_255: (x - mean) / std per
  // channel on the 0..255 pixel values, computed in float64 and rounded to float32 (FluxVLA's TransformImage);
  // a frame of another size is first resized to the resolution with torch-style bilinear (no padding), which is
  // not FluxVLA's PIL resize (a warning says so).
  enum class ImageNorm { lerobot, mean_std_255 };
  ImageNorm image_norm = ImageNorm::lerobot;
  std::vector<std::array<double, 3>> image_mean, image_std;  // per camera in model order (one entry: every camera)
  // Prompt. lerobot: pi0's task + "\n", pi0.5's "Task: ..., State: ...;\nAction: ", through the preprocessor's
  // tokenizer. task_newline: BOS + encode(clean(task)) + encode("\n") with no state (FluxVLA's PaligemmaTokenizer),
  // cut to max_length.
  enum class Prompt { lerobot, task_newline };
  Prompt prompt = Prompt::lerobot;
  std::filesystem::path tokenizer_model;  // task_newline: the SentencePiece file (load_gemma_sentencepiece)
  int max_length = 0;                     // task_newline: tokens kept (FluxVLA's max_len)
  // Attention head counts (query, key/value); nullopt: the Gemma variant's. SigLIP's; nullopt: 72-wide heads.
  std::optional<std::array<int64_t, 2>> vlm_heads, expert_heads;
  std::optional<int64_t> vision_heads;
  // lerobot: sqrt(width) rounded to bf16 when config.json's `dtype` is "bfloat16" (the model is built in it). false:
  // always the float32 root (FluxVLA multiplies by math.sqrt).
  bool embedding_scale_in_config_dtype = true;
  // pi0.5's time. false: lerobot's (times from float64, sinusoid in float64). true: FluxVLA's: the time accumulated
  // in float32 (Schedule::float32_time) and its sinusoid computed in float32 (fluxvla_time_embedding).
  bool float32_time = false;
};

// The models from a checkpoint directory and its opened weights (pi0.cpp).
std::unique_ptr<Model> load_pi0(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                TensorStore weights, const LoadOptions& options);
std::unique_ptr<Model> load_pi05(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                 TensorStore weights, const LoadOptions& options);
// pi0.5 fed as `pizero` says; policy_config holds lerobot's PI05Config fields (what a family converts its own
// config to), the weights lerobot's names.
std::unique_ptr<Model> load_pi05_with(const std::filesystem::path& checkpoint_dir, const Json& policy_config,
                                      TensorStore weights, const LoadOptions& options, const PiZeroOptions& pizero);

// The task_newline prompt's ids: BOS, then the task with Python's strip() and "_" / "\n" replaced by " ", then "\n",
// each encoded without special tokens, cut to max_length (0: uncut). `wrote_special` is set when the text itself
// holds a special token (<bos>, <eos>, <pad>, <unk>): SentencePiece, which FluxVLA runs, spells those out as text,
// while this tokenizer matches them as the token.
struct TaskPrompt {
  std::vector<int32_t> ids;
  bool wrote_special = false;
};
TaskPrompt task_newline_prompt(const text::PretrainedTokenizer& tokenizer, const std::string& task, int max_length);

// FluxVLA's create_sinusoidal_pos_embedding(t, width, min_period, max_period) in float32, operation by operation:
// fraction = linspace(0, 1, width / 2) (torch's float32 linspace), period = min_period * (max / min) ** fraction,
// scale = 1 / period * 2 * pi, [sin(t * scale), cos(t * scale)].
std::vector<float> fluxvla_time_embedding(float time, int64_t width, double min_period, double max_period);

}  // namespace tether::models
