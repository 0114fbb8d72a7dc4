// Request id validation, generation and the seed derived from an id.
#include "serve/request_id.h"

#include <atomic>
#include <cctype>
#include <cstdio>
#include <random>

namespace tether::serve {

bool valid_request_id(const std::string& id) {
  if (id.empty() || id.size() > 128) return false;
  for (char c : id)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == ':' || c == '-')) return false;
  return true;
}

// A per-process random base plus a counter, mixed so consecutive ids do not look sequential.
std::string generate_request_id() {
  static const uint64_t base = [] {
    std::random_device rd;
    return (uint64_t(rd()) << 32) ^ rd();
  }();
  static std::atomic<uint64_t> counter{0};
  uint64_t z = base + 0x9e3779b97f4a7c15ull * (++counter);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  z ^= z >> 31;
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(z));
  return buf;
}

std::string request_id_or_new(std::initializer_list<std::string> offered) {
  for (const auto& id : offered)
    if (valid_request_id(id)) return id;
  return generate_request_id();
}

uint64_t seed_from_request_id(const std::string& id) {
  uint64_t h = 1469598103934665603ull;
  for (char c : id) {
    h ^= static_cast<unsigned char>(c);
    h *= 1099511628211ull;
  }
  return h;
}

}  // namespace tether::serve
