// Times base64 decoding of image-sized payloads: the serve layer's decoder (four lookup tables, one OR per group)
// against the first hand-written table decoder, kept here verbatim as the reference.
// Usage: build/release/bench/base64_decode [FILE...]   (default: a 300 KB JPEG-sized payload and a raw 512x512 RGB
// frame, both incompressible bytes: decode speed depends on the length only, not on what the bytes mean)
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "serve/base64.h"

namespace {

// The decoder serve/base64.cpp had before OpenSSL: a 256-entry reverse table, four characters to three bytes.
constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
constexpr std::array<int8_t, 256> make_reverse() {
  std::array<int8_t, 256> r{};
  for (auto& v : r) v = -1;
  for (int i = 0; i < 64; ++i) r[uint8_t(kAlphabet[i])] = int8_t(i);
  return r;
}
constexpr std::array<int8_t, 256> kReverse = make_reverse();

std::optional<std::vector<uint8_t>> hand_written_decode(std::string_view text) {
  std::size_t n = text.size();
  std::size_t pad = 0;
  while (pad < 2 && n > 0 && text[n - 1] == '=') {
    --n;
    ++pad;
  }
  if (pad > 0 && (n + pad) % 4 != 0) return std::nullopt;
  if (n % 4 == 1) return std::nullopt;
  std::vector<uint8_t> out;
  out.reserve(n / 4 * 3 + 2);
  uint32_t acc = 0;
  int bits = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const int8_t v = kReverse[uint8_t(text[i])];
    if (v < 0) return std::nullopt;
    acc = (acc << 6) | uint32_t(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(uint8_t(acc >> bits));
      acc &= (1u << bits) - 1;
    }
  }
  if (acc != 0) return std::nullopt;
  return out;
}

template <class Decode>
double median_ms(const std::string& text, const std::vector<uint8_t>& expected, Decode decode) {
  if (decode(text) != expected) {
    std::fprintf(stderr, "error: a decoder disagrees with the payload\n");
    std::exit(2);
  }
  std::vector<double> ms;
  for (int i = 0; i < 101; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    const auto out = decode(text);
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    if (!out) std::exit(2);
  }
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

void run(const std::string& label, const std::vector<uint8_t>& bytes) {
  const std::string text = tether::serve::base64_encode(bytes.data(), bytes.size());
  const double mb = double(text.size()) / 1e6;
  const double hand = median_ms(text, bytes, hand_written_decode);
  const double ssl = median_ms(text, bytes, [](const std::string& t) { return tether::serve::base64_decode(t); });
  std::printf("%-28s %8.1f KB base64: hand-written %7.3f ms (%6.0f MB/s), serve %7.3f ms (%6.0f MB/s), %.2fx\n",
              label.c_str(), double(text.size()) / 1e3, hand, mb / (hand / 1e3), ssl, mb / (ssl / 1e3), hand / ssl);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc > 1) {
    for (int i = 1; i < argc; ++i) {
      std::ifstream f(argv[i], std::ios::binary);
      if (!f) {
        std::fprintf(stderr, "error: cannot read %s\n", argv[i]);
        return 2;
      }
      run(argv[i], std::vector<uint8_t>(std::istreambuf_iterator<char>(f), {}));
    }
    return 0;
  }
  std::mt19937 rng(7);
  auto noise = [&](std::size_t n) {
    std::vector<uint8_t> v(n);
    for (auto& b : v) b = uint8_t(rng());
    return v;
  };
  run("512x512 JPEG-sized (300 KB)", noise(300 * 1000));
  run("512x512 raw RGB (786 KB)", noise(512 * 512 * 3));
  return 0;
}
