// Decoded RGB images and the PNG/JPEG decoders. The pixels equal what PIL's
// `Image.open(path).convert("RGB")` yields, which is what lerobot feeds its policies.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace tether::vision {

struct Image {
  int height = 0, width = 0;
  std::vector<uint8_t> rgb;  // height x width x 3, row-major
};

// Decompression-bomb guard: larger images are refused before any pixel buffer is allocated.
inline constexpr int64_t kMaxImagePixels = 100'000'000;

// Decodes PNG or JPEG, chosen by the magic bytes. `label` names the source (file, request field) in
// errors. EXIF orientation is deliberately NOT applied: PIL's plain open/convert ignores it, and
// the upstream policy saw the pixels in stored order.
Image decode_image(const uint8_t* bytes, std::size_t size, const std::string& label);
Image decode_png(const uint8_t* bytes, std::size_t size, const std::string& label);
Image decode_jpeg(const uint8_t* bytes, std::size_t size, const std::string& label);

// Reads and decodes a file; the path is the label.
Image load_image(const std::string& path);

}  // namespace tether::vision
