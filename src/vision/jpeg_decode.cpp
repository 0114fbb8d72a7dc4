// JPEG decoding with TurboJPEG, set up to produce the same pixels as PIL (which wraps
// libjpeg-turbo): the accurate integer IDCT (JDCT_ISLOW) and "fancy" (triangle-filter) chroma
// upsampling.
#include <turbojpeg.h>

#include <cstring>
#include <memory>

#include "core/error.h"
#include "vision/image.h"

namespace tether::vision {

namespace {

struct TjDeleter {
  void operator()(void* handle) const { tjDestroy(handle); }
};

}  // namespace

Image decode_jpeg(const uint8_t* bytes, std::size_t size, const std::string& label) {
  std::unique_ptr<void, TjDeleter> handle(tjInitDecompress());
  if (!handle) throw Error(ErrorCode::internal, label + ": cannot create JPEG decoder");
  tjhandle tj = handle.get();

  int width = 0, height = 0, subsamp = 0, colorspace = 0;
  if (tjDecompressHeader3(tj, bytes, static_cast<unsigned long>(size), &width, &height, &subsamp,
                          &colorspace) != 0)
    throw Error(ErrorCode::format, label + ": invalid JPEG header: " + tjGetErrorStr2(tj));
  if (width <= 0 || height <= 0) throw Error(ErrorCode::format, label + ": JPEG has zero size");
  if (int64_t(width) * height > kMaxImagePixels)
    throw Error(ErrorCode::invalid_argument, label + ": JPEG is " + std::to_string(width) + "x" +
                                                 std::to_string(height) + ", over the limit of " +
                                                 std::to_string(kMaxImagePixels) + " pixels");
  // PIL would return these in mode CMYK and apply its own naive CMYK->RGB formula; robot cameras
  // do not produce them, so they are refused rather than approximated.
  if (colorspace == TJCS_CMYK || colorspace == TJCS_YCCK)
    throw Error(ErrorCode::unsupported, label + ": CMYK/YCCK JPEG is not supported");

  Image img;
  img.width = width;
  img.height = height;
  img.rgb.resize(std::size_t(width) * std::size_t(height) * 3);
  // ACCURATEDCT = JDCT_ISLOW, PIL's default; not passing FASTUPSAMPLE keeps fancy upsampling on.
  // LIMITSCANS refuses progressive files with an absurd number of scans (a CPU-exhaustion attack).
  const int flags = TJFLAG_ACCURATEDCT | TJFLAG_LIMITSCANS;
  if (tjDecompress2(tj, bytes, static_cast<unsigned long>(size), img.rgb.data(), width, 0, height,
                    TJPF_RGB, flags) != 0) {
    const std::string msg = tjGetErrorStr2(tj);
    // libjpeg reports most corruption as warnings and keeps decoding, and PIL ignores them too,
    // except running out of data: PIL raises "image file is truncated", so a truncated file is an
    // error here as well.
    const bool warning_only = tjGetErrorCode(tj) == TJERR_WARNING;
    if (!warning_only || msg.find("Premature end of JPEG file") != std::string::npos)
      throw Error(ErrorCode::format, label + ": cannot decode JPEG: " + msg);
  }
  return img;
}

}  // namespace tether::vision
