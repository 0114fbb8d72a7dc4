// Reader for the safetensors format: the file is mmap'ed once and tensors are zero-copy views into it.
// Every structural claim of the header (offsets, shapes, dtypes) is checked before any view is handed out.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/tensor.h"

namespace tether {

struct TensorEntry {
  DType dtype;
  Shape shape;
  uint64_t begin = 0;  // byte offsets relative to the start of the data region
  uint64_t end = 0;
};

struct SafeTensorsHeader {
  std::map<std::string, TensorEntry> tensors;
  std::map<std::string, std::string> metadata;
  uint64_t data_offset = 0;  // where the data region starts in the file
};

// Parses and validates the header of a safetensors byte buffer (the whole file). `label` names the file in
// errors. Exposed separately so the fuzzer can drive it without touching the filesystem.
SafeTensorsHeader parse_safetensors_header(const uint8_t* bytes, std::size_t size, const std::string& label);

class SafeTensorsFile {
 public:
  static SafeTensorsFile open(const std::string& path);

  const std::string& path() const { return path_; }
  bool contains(const std::string& name) const { return header_.tensors.count(name) != 0; }
  std::vector<std::string> names() const;
  const std::map<std::string, std::string>& metadata() const { return header_.metadata; }
  const TensorEntry& entry(const std::string& name) const;  // throws not_found naming file and tensor

  // Zero-copy view; the returned tensor keeps the mapping alive.
  Tensor get(const std::string& name) const;

  // Tells the kernel the mapped pages are not needed now: they leave this process's resident set and are
  // read back from the page cache on the next access. For after load, once the weights were copied out.
  void drop_resident_pages() const;
  // The same for the pages holding one tensor (a neighbour sharing an edge page just faults it back in).
  void drop_resident_pages(const std::string& name) const;

 private:
  std::string path_;
  std::shared_ptr<const void> mapping_;
  const uint8_t* base_ = nullptr;
  std::size_t size_ = 0;
  SafeTensorsHeader header_;
};

// Writes tensors to a safetensors file (used by tests and the exporter). Tensors are written in name order.
void write_safetensors(const std::string& path, const std::map<std::string, Tensor>& tensors,
                       const std::map<std::string, std::string>& metadata = {});

}  // namespace tether
