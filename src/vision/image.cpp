// Format detection by magic bytes and file loading; the decoders live in png_decode.cpp and
// jpeg_decode.cpp.
#include "vision/image.h"

#include <cerrno>
#include <cstring>
#include <fstream>

#include "core/error.h"

namespace tether::vision {

namespace {

constexpr uint8_t kPngMagic[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};

bool starts_with(const uint8_t* bytes, std::size_t size, const uint8_t* magic, std::size_t n) {
  return size >= n && std::memcmp(bytes, magic, n) == 0;
}

}  // namespace

Image decode_image(const uint8_t* bytes, std::size_t size, const std::string& label) {
  if (bytes == nullptr || size == 0)
    throw Error(ErrorCode::format, label + ": image data is empty");
  if (starts_with(bytes, size, kPngMagic, sizeof(kPngMagic))) return decode_png(bytes, size, label);
  constexpr uint8_t kJpegMagic[3] = {0xff, 0xd8, 0xff};
  if (starts_with(bytes, size, kJpegMagic, sizeof(kJpegMagic)))
    return decode_jpeg(bytes, size, label);
  static const char* kHex = "0123456789abcdef";
  std::string head;
  for (std::size_t i = 0; i < std::min<std::size_t>(size, 8); ++i) {
    head += kHex[bytes[i] >> 4];
    head += kHex[bytes[i] & 15];
  }
  throw Error(ErrorCode::unsupported,
              label + ": unknown image format (first bytes 0x" + head + "); expected PNG or JPEG");
}

Image load_image(const std::string& path) {
  std::ifstream f(path, std::ios::binary | std::ios::ate);
  if (!f) {
    const int err = errno;
    throw Error(err == ENOENT ? ErrorCode::not_found : ErrorCode::io,
                path + ": cannot open image: " + std::strerror(err));
  }
  const std::streamoff size = f.tellg();
  if (size < 0) throw Error(ErrorCode::io, path + ": cannot determine file size");
  std::vector<uint8_t> bytes(static_cast<std::size_t>(size));
  f.seekg(0);
  if (size > 0 && !f.read(reinterpret_cast<char*>(bytes.data()), size))
    throw Error(ErrorCode::io, path + ": read failed");
  return decode_image(bytes.data(), bytes.size(), path);
}

}  // namespace tether::vision
