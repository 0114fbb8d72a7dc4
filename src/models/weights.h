// A checkpoint's tensors and checked access to them: every weight is verified for name, shape and dtype before use.
// The tensors come from one safetensors file or from the shards a `model.safetensors.index.json` names; either way
// they are looked up by name, and errors name the file (the shard) that holds the tensor.
// float32 tensors are used in place from the mmap; bf16/f16 (and misaligned f32) tensors are copied to float32
// once at load time.
#pragma once

#include <deque>
#include <map>
#include <string>
#include <vector>

#include "backend/cpu/packed_linear.h"
#include "core/safetensors.h"

namespace tether::models {

// The conventional file names: one file, or an index naming shards.
inline constexpr const char* kSingleWeightsFile = "model.safetensors";
inline constexpr const char* kShardIndexFile = "model.safetensors.index.json";

// Tensors by name over one or several safetensors files.
class TensorStore {
 public:
  TensorStore() = default;
  explicit TensorStore(SafeTensorsFile file);
  // One safetensors file.
  static TensorStore open_file(const std::string& path);
  // The shards named by a Hugging Face index ({"weight_map": {tensor: shard file}}), relative to the index's
  // directory. Every shard is opened and every mapped tensor checked to be in its shard; errors name the index and
  // the shard.
  static TensorStore open_index(const std::string& index_path);
  // `dir`'s weights: the index when `dir` has kShardIndexFile, else kSingleWeightsFile.
  static TensorStore open_dir(const std::string& dir);
  // The weight files of `dir` (relative names), as open_dir would read them: the index and its shards, or the
  // single file. Empty when there are none. Does not open the shards.
  static std::vector<std::string> files_in(const std::string& dir);

  // The index or the single file: what errors about a missing tensor name.
  const std::string& label() const { return label_; }
  // The safetensors files, in the order the index first names them.
  std::vector<std::string> paths() const;
  bool sharded() const { return sharded_; }

  bool contains(const std::string& name) const { return where_.count(name) != 0; }
  std::vector<std::string> names() const;  // sorted
  const TensorEntry& entry(const std::string& name) const;  // throws not_found naming label() and the tensor
  Tensor get(const std::string& name) const;                // zero-copy view
  const std::string& file_of(const std::string& name) const;

  // Takes tensors out of the model's view (a family's converter moved them elsewhere, e.g. legacy statistics).
  void hide(const std::string& name);
  // Renames every tensor whose name contains `fragment` to the name without it (torch.compile's "._orig_mod").
  void strip_from_names(const std::string& fragment);
  // Gives tensor `from` the name `to` (a key rename upstream applies on load); false when there is no `from`. An
  // existing `to` is replaced, as a later key of a state dict replaces an earlier one.
  bool rename(const std::string& from, const std::string& to);

  void drop_resident_pages() const;
  void drop_resident_pages(const std::string& name) const;

 private:
  struct Location {
    std::size_t file = 0;
    std::string stored;  // the name in that file
  };
  const Location& locate(const std::string& name) const;

  std::vector<SafeTensorsFile> files_;
  std::map<std::string, Location> where_;
  std::string label_;
  bool sharded_ = false;
};

class Weights {
 public:
  explicit Weights(TensorStore store) : store_(std::move(store)) {}
  explicit Weights(SafeTensorsFile file) : store_(std::move(file)) {}

  const std::string& path() const { return store_.label(); }
  const TensorStore& store() const { return store_; }
  bool contains(const std::string& name) const { return store_.contains(name); }

  // Float32 view of tensor `name`, which must have exactly `shape`; errors name the file and tensor.
  const float* f32(const std::string& name, const Shape& shape);

  // Several checked tensors converted straight into one float32 buffer, one after another (fused q/k/v or
  // gate/up weights), without an intermediate copy of each.
  std::vector<float> stacked(const std::vector<std::pair<std::string, Shape>>& parts);

  // Checked view in the stored dtype, for tables read a row at a time (token embeddings).
  Tensor raw(const std::string& name, const Shape& shape);

  // After load: the files' pages leave the resident set. Linear weights live in packed copies; the few tensors
  // still read from the mapping (norm weights, embedding rows) fault their pages back in on demand.
  void finish_loading();

  // Dtype of the checkpoint's floating-point weights ("F32", "BF16", ...) as found at load time.
  std::string stored_dtype() const { return stored_dtype_; }

 private:
  const TensorEntry& checked(const std::string& name, const Shape& shape);

  TensorStore store_;
  std::deque<std::vector<float>> widened_;  // owned float32 copies of bf16/f16 tensors
  std::string stored_dtype_;
};


}  // namespace tether::models
