// PNG decoding with libspng, converted to 8-bit RGB by the same rules as PIL's convert("RGB"):
// alpha and tRNS are dropped (no compositing), 16-bit colour keeps the high byte, 16-bit grey is
// clipped to 255 (PIL goes through mode "I;16"), low-bit grey is scaled to 0..255, and palette
// indices beyond the palette become black. gAMA/iCCP are ignored, as PIL ignores them.
#include <spng.h>

#include <algorithm>
#include <cstring>
#include <memory>

#include "core/error.h"
#include "vision/image.h"

namespace tether::vision {

namespace {

// Ancillary chunks (text, ICC profiles) that libspng keeps in memory are capped so a hostile file
// cannot make us allocate without bound before a single pixel is decoded.
constexpr std::size_t kChunkCacheLimit = 64u << 20;

struct SpngDeleter {
  void operator()(spng_ctx* ctx) const { spng_ctx_free(ctx); }
};

[[noreturn]] void fail(const std::string& label, const std::string& what, int rc) {
  throw Error(ErrorCode::format, label + ": invalid PNG: " + what + " (" + spng_strerror(rc) + ")");
}

// Sample `i` of a row packed at `depth` bits per sample, most significant bits first (PNG order).
inline unsigned packed_sample(const uint8_t* row, int64_t i, int depth) {
  const int64_t bit = i * depth;
  const unsigned byte = row[bit >> 3];
  const int shift = 8 - depth - int(bit & 7);
  return (byte >> shift) & ((1u << depth) - 1u);
}

// 16-bit samples arrive in host order; memcpy keeps the read free of alignment and aliasing traps.
inline unsigned sample16(const uint8_t* row, int64_t i) {
  uint16_t v;
  std::memcpy(&v, row + 2 * i, 2);
  return v;
}

}  // namespace

Image decode_png(const uint8_t* bytes, std::size_t size, const std::string& label) {
  std::unique_ptr<spng_ctx, SpngDeleter> ctx(spng_ctx_new(0));
  if (!ctx) throw Error(ErrorCode::internal, label + ": cannot create PNG decoder");
  spng_ctx* c = ctx.get();
  int rc = spng_set_png_buffer(c, bytes, size);
  if (rc) fail(label, "cannot read buffer", rc);
  spng_set_chunk_limits(c, 0x7fffffff, kChunkCacheLimit);

  spng_ihdr ihdr{};
  rc = spng_get_ihdr(c, &ihdr);
  if (rc) fail(label, "bad header", rc);
  const int64_t pixels = int64_t(ihdr.width) * int64_t(ihdr.height);
  if (pixels > kMaxImagePixels)
    throw Error(ErrorCode::invalid_argument, label + ": PNG is " + std::to_string(ihdr.width) +
                                                 "x" + std::to_string(ihdr.height) +
                                                 ", over the limit of " +
                                                 std::to_string(kMaxImagePixels) + " pixels");

  std::size_t raw_size = 0;
  rc = spng_decoded_image_size(c, SPNG_FMT_PNG, &raw_size);
  if (rc) fail(label, "cannot size image", rc);
  std::vector<uint8_t> raw(raw_size);
  // SPNG_FMT_PNG keeps the file's own sample layout (16-bit samples in host order, low depths
  // packed); all conversions below are ours so they follow PIL, not libspng's own rules.
  rc = spng_decode_image(c, raw.data(), raw.size(), SPNG_FMT_PNG, 0);
  if (rc) fail(label, "cannot decode pixels", rc);

  const int w = int(ihdr.width), h = int(ihdr.height), depth = ihdr.bit_depth;
  const std::size_t stride = raw_size / std::size_t(h);
  Image img;
  img.width = w;
  img.height = h;
  img.rgb.resize(std::size_t(pixels) * 3);
  uint8_t* out = img.rgb.data();

  spng_plte plte{};
  if (ihdr.color_type == SPNG_COLOR_TYPE_INDEXED) {
    rc = spng_get_plte(c, &plte);
    if (rc) fail(label, "indexed image without a usable palette", rc);
  }

  for (int y = 0; y < h; ++y) {
    const uint8_t* row = raw.data() + std::size_t(y) * stride;
    uint8_t* o = out + std::size_t(y) * std::size_t(w) * 3;
    switch (ihdr.color_type) {
      case SPNG_COLOR_TYPE_GRAYSCALE:
        for (int x = 0; x < w; ++x, o += 3) {
          unsigned v;
          if (depth == 16) {
            v = std::min(sample16(row, x), 255u);
          } else if (depth == 8) {
            v = row[x];
          } else {
            v = packed_sample(row, x, depth) * (255u / ((1u << depth) - 1u));
          }
          o[0] = o[1] = o[2] = uint8_t(v);
        }
        break;
      case SPNG_COLOR_TYPE_TRUECOLOR:
      case SPNG_COLOR_TYPE_TRUECOLOR_ALPHA: {
        const int n = ihdr.color_type == SPNG_COLOR_TYPE_TRUECOLOR ? 3 : 4;
        for (int x = 0; x < w; ++x, o += 3)
          for (int k = 0; k < 3; ++k)
            o[k] = depth == 16 ? uint8_t(sample16(row, x * n + k) >> 8) : row[x * n + k];
        break;
      }
      case SPNG_COLOR_TYPE_GRAYSCALE_ALPHA:
        for (int x = 0; x < w; ++x, o += 3)
          o[0] = o[1] = o[2] = depth == 16 ? uint8_t(sample16(row, 2 * x) >> 8) : row[2 * x];
        break;
      case SPNG_COLOR_TYPE_INDEXED:
        for (int x = 0; x < w; ++x, o += 3) {
          const unsigned i = depth == 8 ? row[x] : packed_sample(row, x, depth);
          if (i < plte.n_entries) {
            o[0] = plte.entries[i].red;
            o[1] = plte.entries[i].green;
            o[2] = plte.entries[i].blue;
          } else {
            o[0] = o[1] = o[2] = 0;
          }
        }
        break;
      default:
        throw Error(
            ErrorCode::unsupported,
            label + ": PNG colour type " + std::to_string(ihdr.color_type) + " is not supported");
    }
  }
  return img;
}

}  // namespace tether::vision
