// SHA-256 (FIPS 180-4) for the model hash the server reports, so a client can tell exactly which weights answered.
// Self-contained: the only user is this hash of a local file, not worth a crypto library dependency.
#pragma once

#include <array>
#include <cstdint>
#include <string>

namespace tether::serve {

class Sha256 {
 public:
  Sha256();
  void update(const uint8_t* data, std::size_t size);
  std::array<uint8_t, 32> finish();

 private:
  void block(const uint8_t* p);
  std::array<uint32_t, 8> h_;
  std::array<uint8_t, 64> buf_{};
  std::size_t buf_len_ = 0;
  uint64_t total_ = 0;
};

std::string to_hex(const uint8_t* bytes, std::size_t size);
// Lower-case hex digest of a file's contents; throws tether::Error(io) when it cannot be read.
std::string sha256_file_hex(const std::string& path);

}  // namespace tether::serve
