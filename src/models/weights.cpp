// Tensors over one file or an index's shards, and the checked float32 access the model blocks load through.
#include "models/weights.h"

#include <algorithm>
#include <filesystem>
#include <set>

#include "core/error.h"
#include "core/json_util.h"

namespace tether::models {

namespace fs = std::filesystem;

TensorStore::TensorStore(SafeTensorsFile file) : label_(file.path()) {
  for (const auto& name : file.names()) where_[name] = {0, name};
  files_.push_back(std::move(file));
}

TensorStore TensorStore::open_file(const std::string& path) { return TensorStore(SafeTensorsFile::open(path)); }

TensorStore TensorStore::open_index(const std::string& index_path) {
  const Json index = read_json_file(index_path);
  const auto map = index.find("weight_map");
  if (!index.is_object() || map == index.end() || !map->is_object() || map->empty())
    throw Error(ErrorCode::format, index_path + ": no \"weight_map\" object naming the shards of each tensor");
  TensorStore s;
  s.label_ = index_path;
  s.sharded_ = true;
  const fs::path dir = fs::path(index_path).parent_path();
  std::map<std::string, std::size_t> shard_index;
  std::map<std::string, std::vector<std::string>> held;  // shard -> tensors the index puts there
  std::vector<std::string> order;
  for (auto it = map->begin(); it != map->end(); ++it) {
    if (!it->is_string())
      throw Error(ErrorCode::format, index_path + ": weight_map['" + it.key() + "'] is not a file name");
    const std::string shard = it->get<std::string>();
    const fs::path rel(shard);
    if (shard.empty() || rel.is_absolute() ||
        std::any_of(rel.begin(), rel.end(), [](const fs::path& part) { return part == ".."; }))
      throw Error(ErrorCode::format, index_path + ": shard '" + shard + "' (of tensor '" + it.key() +
                                         "') is not a file name inside the checkpoint directory");
    if (!held.count(shard)) order.push_back(shard);
    held[shard].push_back(it.key());
  }
  for (const auto& shard : order) {
    const fs::path path = dir / shard;
    if (!fs::is_regular_file(path))
      throw Error(ErrorCode::not_found, index_path + ": shard '" + shard + "' (" + std::to_string(held[shard].size()) +
                                            " tensors, e.g. '" + held[shard].front() + "') is missing: " + path.string());
    shard_index[shard] = s.files_.size();
    s.files_.push_back(SafeTensorsFile::open(path.string()));
  }
  for (auto it = map->begin(); it != map->end(); ++it) {
    const std::string& shard = it->get_ref<const std::string&>();
    const std::size_t f = shard_index.at(shard);
    if (!s.files_[f].contains(it.key()))
      throw Error(ErrorCode::format, s.files_[f].path() + ": has no tensor '" + it.key() + "', which " + index_path +
                                         " maps to this shard");
    s.where_[it.key()] = {f, it.key()};
  }
  return s;
}

TensorStore TensorStore::open_dir(const std::string& dir) {
  const fs::path index = fs::path(dir) / kShardIndexFile;
  if (fs::is_regular_file(index)) return open_index(index.string());
  return open_file((fs::path(dir) / kSingleWeightsFile).string());
}

std::vector<std::string> TensorStore::files_in(const std::string& dir) {
  const fs::path index = fs::path(dir) / kShardIndexFile;
  if (!fs::is_regular_file(index))
    return fs::is_regular_file(fs::path(dir) / kSingleWeightsFile) ? std::vector<std::string>{kSingleWeightsFile}
                                                                     : std::vector<std::string>{};
  std::vector<std::string> out = {kShardIndexFile};
  const Json j = read_json_file(index.string());
  std::set<std::string> seen;
  if (j.contains("weight_map") && j["weight_map"].is_object())
    for (const auto& shard : j["weight_map"])
      if (shard.is_string() && seen.insert(shard.get<std::string>()).second) out.push_back(shard.get<std::string>());
  return out;
}

std::vector<std::string> TensorStore::paths() const {
  std::vector<std::string> out;
  for (const auto& f : files_) out.push_back(f.path());
  return out;
}

std::vector<std::string> TensorStore::names() const {
  std::vector<std::string> out;
  for (const auto& [name, _] : where_) out.push_back(name);
  return out;
}

const TensorStore::Location& TensorStore::locate(const std::string& name) const {
  auto it = where_.find(name);
  if (it == where_.end())
    throw Error(ErrorCode::not_found, label_ + ": missing tensor '" + name + "'" +
                                          (sharded_ ? " (not in the index's weight_map)" : ""));
  return it->second;
}

const TensorEntry& TensorStore::entry(const std::string& name) const {
  const Location& l = locate(name);
  return files_[l.file].entry(l.stored);
}

Tensor TensorStore::get(const std::string& name) const {
  const Location& l = locate(name);
  return files_[l.file].get(l.stored);
}

const std::string& TensorStore::file_of(const std::string& name) const { return files_[locate(name).file].path(); }

void TensorStore::hide(const std::string& name) { where_.erase(name); }

void TensorStore::strip_from_names(const std::string& fragment) {
  if (fragment.empty()) return;
  std::map<std::string, Location> renamed;
  for (auto& [name, loc] : where_) {
    std::string n = name;
    for (std::size_t at; (at = n.find(fragment)) != std::string::npos;) n.erase(at, fragment.size());
    renamed[n] = std::move(loc);  // like a dict comprehension: a later duplicate wins
  }
  where_ = std::move(renamed);
}

bool TensorStore::rename(const std::string& from, const std::string& to) {
  auto it = where_.find(from);
  if (it == where_.end()) return false;
  Location loc = std::move(it->second);
  where_.erase(it);
  where_[to] = std::move(loc);
  return true;
}

void TensorStore::drop_resident_pages() const {
  for (const auto& f : files_) f.drop_resident_pages();
}

void TensorStore::drop_resident_pages(const std::string& name) const {
  const Location& l = locate(name);
  files_[l.file].drop_resident_pages(l.stored);
}

const TensorEntry& Weights::checked(const std::string& name, const Shape& shape) {
  const TensorEntry& e = store_.entry(name);
  if (e.shape != shape)
    throw Error(ErrorCode::format, store_.file_of(name) + ": tensor '" + name + "' has shape " + shape_str(e.shape) +
                                       ", the config implies " + shape_str(shape));
  if (e.dtype != DType::f32 && e.dtype != DType::bf16 && e.dtype != DType::f16)
    throw Error(ErrorCode::unsupported, store_.file_of(name) + ": tensor '" + name + "' has dtype " +
                                            std::string(dtype_name(e.dtype)) + ", expected F32, BF16 or F16");
  if (stored_dtype_.empty()) stored_dtype_ = std::string(dtype_name(e.dtype));
  return e;
}

const float* Weights::f32(const std::string& name, const Shape& shape) {
  checked(name, shape);
  Tensor t = store_.get(name);
  if (t.dtype == DType::f32 && t.aligned()) return t.as<float>();  // in place from the mmap
  widened_.push_back(t.to_f32());
  store_.drop_resident_pages(name);  // copied out: keep peak memory at one copy of the weights
  return widened_.back().data();
}

std::vector<float> Weights::stacked(const std::vector<std::pair<std::string, Shape>>& parts) {
  int64_t total = 0;
  for (const auto& [name, shape] : parts) total += shape_numel(shape);
  std::vector<float> out(static_cast<std::size_t>(total));
  int64_t at = 0;
  for (const auto& [name, shape] : parts) {
    checked(name, shape);
    const Tensor t = store_.get(name);
    t.copy_f32(0, t.numel(), out.data() + at);
    at += t.numel();
    store_.drop_resident_pages(name);  // copied out
  }
  return out;
}

Tensor Weights::raw(const std::string& name, const Shape& shape) {
  checked(name, shape);
  return store_.get(name);  // rows fault in on demand, so it does not pin the file's pages
}

void Weights::finish_loading() { store_.drop_resident_pages(); }

}  // namespace tether::models
