// The safetensors reader (mmap, checked header, zero-copy views) and writer (see safetensors.h).
#include "core/safetensors.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>

#include "core/error.h"

namespace tether {

namespace {

// The format caps the header at 100 MB; anything larger is a corrupt or hostile length prefix.
constexpr uint64_t kMaxHeaderBytes = 100ull * 1024 * 1024;
// The schema nests 3 deep ({name: {"shape": [...]}}). Deeper input is refused while parsing: a 100 MB header of
// nested brackets would otherwise overflow the stack in the recursive dump() that names a bad field.
constexpr int kMaxHeaderDepth = 16;

[[noreturn]] void fail(const std::string& label, const std::string& what) {
  throw Error(ErrorCode::format, label + ": " + what);
}

uint64_t read_le64(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}

TensorEntry parse_entry(const nlohmann::json& j, const std::string& label, const std::string& name,
                        uint64_t data_size) {
  const std::string where = "tensor '" + name + "'";
  if (!j.is_object()) fail(label, where + " header entry is not an object");
  auto dtype_it = j.find("dtype");
  auto shape_it = j.find("shape");
  auto offsets_it = j.find("data_offsets");
  if (dtype_it == j.end() || !dtype_it->is_string()) fail(label, where + " has no string 'dtype'");
  if (shape_it == j.end() || !shape_it->is_array()) fail(label, where + " has no array 'shape'");
  if (offsets_it == j.end() || !offsets_it->is_array() || offsets_it->size() != 2)
    fail(label, where + " has no two-element 'data_offsets'");

  TensorEntry e;
  const std::string dtype_name_str = dtype_it->get<std::string>();
  if (!dtype_from_name(dtype_name_str, &e.dtype))
    throw Error(ErrorCode::unsupported, label + ": " + where + " has unknown dtype '" + dtype_name_str + "'");

  // Count bytes with overflow checks: a lying shape must not wrap around to a plausible size. The bound is
  // INT64_MAX, not UINT64_MAX: dims and element counts are int64_t (Tensor::numel() multiplies the dims left to
  // right), and a zero dim after huge ones still leaves those partial products to overflow.
  constexpr uint64_t kMax = uint64_t(INT64_MAX);
  uint64_t bytes = dtype_size(e.dtype);
  for (const auto& d : *shape_it) {
    if (!d.is_number_unsigned()) fail(label, where + " shape " + shape_it->dump() + " is not non-negative integers");
    const uint64_t dim = d.get<uint64_t>();
    if (dim > kMax || (dim != 0 && bytes > kMax / dim))
      fail(label, where + " shape " + shape_it->dump() + " overflows");
    bytes *= dim;
    e.shape.push_back(int64_t(dim));
  }
  for (const auto& o : *offsets_it)
    if (!o.is_number_unsigned()) fail(label, where + " data_offsets are not non-negative integers");
  e.begin = (*offsets_it)[0].get<uint64_t>();
  e.end = (*offsets_it)[1].get<uint64_t>();
  if (e.begin > e.end) fail(label, where + " data_offsets begin > end");
  if (e.end > data_size)
    fail(label, where + " data_offsets [" + std::to_string(e.begin) + ", " + std::to_string(e.end) +
                    ") run past the end of the data (" + std::to_string(data_size) + " bytes; file truncated?)");
  if (e.end - e.begin != bytes)
    fail(label, where + " shape " + shape_str(e.shape) + " " + dtype_name_str + " needs " + std::to_string(bytes) +
                    " bytes but data_offsets span " + std::to_string(e.end - e.begin));
  return e;
}

struct Mapping {
  void* addr = nullptr;
  std::size_t size = 0;
  ~Mapping() {
    if (addr && size) munmap(addr, size);
  }
};

}  // namespace

SafeTensorsHeader parse_safetensors_header(const uint8_t* bytes, std::size_t size, const std::string& label) {
  if (size < 8) fail(label, "file is " + std::to_string(size) + " bytes, too short for a safetensors header");
  const uint64_t header_len = read_le64(bytes);
  if (header_len > kMaxHeaderBytes) fail(label, "header length " + std::to_string(header_len) + " is implausible");
  if (header_len > size - 8)
    fail(label, "header length " + std::to_string(header_len) + " exceeds the file size (truncated?)");

  auto depth_guard = [&](int depth, nlohmann::json::parse_event_t, nlohmann::json&) {
    if (depth > kMaxHeaderDepth) fail(label, "header JSON nests deeper than " + std::to_string(kMaxHeaderDepth) + " levels");
    return true;
  };
  nlohmann::json j = nlohmann::json::parse(bytes + 8, bytes + 8 + header_len, depth_guard, /*allow_exceptions=*/false);
  if (j.is_discarded()) fail(label, "header is not valid JSON");
  if (!j.is_object()) fail(label, "header is not a JSON object");

  SafeTensorsHeader h;
  h.data_offset = 8 + header_len;
  const uint64_t data_size = size - h.data_offset;
  for (auto it = j.begin(); it != j.end(); ++it) {
    if (it.key() == "__metadata__") {
      if (!it->is_object()) fail(label, "__metadata__ is not an object");
      for (auto m = it->begin(); m != it->end(); ++m) {
        if (!m->is_string()) fail(label, "__metadata__ value '" + m.key() + "' is not a string");
        h.metadata[m.key()] = m->get<std::string>();
      }
      continue;
    }
    h.tensors[it.key()] = parse_entry(*it, label, it.key(), data_size);
  }

  // Tensors must not share bytes: overlapping ranges mean the header lies about its layout.
  std::vector<std::pair<const std::string*, const TensorEntry*>> order;
  for (const auto& [name, e] : h.tensors)
    if (e.end > e.begin) order.push_back({&name, &e});
  std::sort(order.begin(), order.end(), [](auto a, auto b) { return a.second->begin < b.second->begin; });
  for (std::size_t i = 1; i < order.size(); ++i)
    if (order[i].second->begin < order[i - 1].second->end)
      fail(label, "tensors '" + *order[i - 1].first + "' and '" + *order[i].first + "' overlap");
  return h;
}

SafeTensorsFile SafeTensorsFile::open(const std::string& path) {
  int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    throw Error(errno == ENOENT ? ErrorCode::not_found : ErrorCode::io,
                path + ": cannot open (" + std::strerror(errno) + ")");
  }
  struct stat st {};
  if (fstat(fd, &st) != 0) {
    const int err = errno;
    ::close(fd);
    throw Error(ErrorCode::io, path + ": cannot stat (" + std::strerror(err) + ")");
  }
  auto mapping = std::make_shared<Mapping>();
  mapping->size = std::size_t(st.st_size);
  if (mapping->size > 0) {
    void* addr = mmap(nullptr, mapping->size, PROT_READ, MAP_PRIVATE, fd, 0);
    if (addr == MAP_FAILED) {
      const int err = errno;
      ::close(fd);
      throw Error(ErrorCode::io, path + ": mmap failed (" + std::strerror(err) + ")");
    }
    mapping->addr = addr;
  }
  ::close(fd);

  SafeTensorsFile f;
  f.path_ = path;
  f.base_ = static_cast<const uint8_t*>(mapping->addr);
  f.size_ = mapping->size;
  f.header_ = parse_safetensors_header(f.base_, mapping->size, path);
  f.mapping_ = std::shared_ptr<const void>(mapping, mapping->addr);
  return f;
}

void SafeTensorsFile::drop_resident_pages() const {
  if (base_ && size_) madvise(const_cast<uint8_t*>(base_), size_, MADV_DONTNEED);
}

void SafeTensorsFile::drop_resident_pages(const std::string& name) const {
  const TensorEntry& e = entry(name);
  static const uintptr_t page = uintptr_t(sysconf(_SC_PAGESIZE));
  const uintptr_t begin = reinterpret_cast<uintptr_t>(base_ + header_.data_offset + e.begin) & ~(page - 1);
  const uintptr_t end = reinterpret_cast<uintptr_t>(base_ + header_.data_offset + e.end);
  if (end > begin) madvise(reinterpret_cast<void*>(begin), end - begin, MADV_DONTNEED);
}

std::vector<std::string> SafeTensorsFile::names() const {
  std::vector<std::string> out;
  for (const auto& [name, _] : header_.tensors) out.push_back(name);
  return out;
}

const TensorEntry& SafeTensorsFile::entry(const std::string& name) const {
  auto it = header_.tensors.find(name);
  if (it == header_.tensors.end()) throw Error(ErrorCode::not_found, path_ + ": missing tensor '" + name + "'");
  return it->second;
}

Tensor SafeTensorsFile::get(const std::string& name) const {
  const TensorEntry& e = entry(name);
  Tensor t;
  t.dtype = e.dtype;
  t.shape = e.shape;
  t.data = base_ + header_.data_offset + e.begin;
  t.owner = mapping_;
  return t;
}

void write_safetensors(const std::string& path, const std::map<std::string, Tensor>& tensors,
                       const std::map<std::string, std::string>& metadata) {
  nlohmann::json header = nlohmann::json::object();
  if (!metadata.empty()) header["__metadata__"] = metadata;
  uint64_t offset = 0;
  for (const auto& [name, t] : tensors) {
    header[name] = {{"dtype", std::string(dtype_name(t.dtype))},
                    {"shape", t.shape},
                    {"data_offsets", {offset, offset + t.nbytes()}}};
    offset += t.nbytes();
  }
  std::string text = header.dump();
  while ((text.size() + 8) % 8 != 0) text += ' ';  // keep the data region 8-byte aligned
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) throw Error(ErrorCode::io, path + ": cannot open for writing");
  uint8_t len[8];
  for (int i = 0; i < 8; ++i) len[i] = uint8_t(uint64_t(text.size()) >> (8 * i));
  out.write(reinterpret_cast<const char*>(len), 8);
  out.write(text.data(), std::streamsize(text.size()));
  for (const auto& [name, t] : tensors) out.write(static_cast<const char*>(t.data), std::streamsize(t.nbytes()));
  if (!out) throw Error(ErrorCode::io, path + ": write failed");
}

}  // namespace tether
