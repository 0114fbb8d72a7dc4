// The Hugging Face cache root, in huggingface_hub's precedence.
#include "core/hf_paths.h"

#include <pwd.h>
#include <unistd.h>

#include <cctype>
#include <cstdlib>

namespace tether {

namespace {

std::string env(const char* name) {
  const char* v = std::getenv(name);
  return v ? std::string(v) : std::string();
}

std::string user_home() {
  if (const char* h = std::getenv("HOME")) return h;  // os.path.expanduser: $HOME, even when empty
  if (const passwd* pw = ::getpwuid(::getuid()); pw && pw->pw_dir) return pw->pw_dir;
  return "/";
}

}  // namespace

std::string expand_user_and_vars(const std::string& path) {
  std::string p = path;
  if (!p.empty() && p[0] == '~' && (p.size() == 1 || p[1] == '/')) p = user_home() + p.substr(1);
  std::string out;
  for (std::size_t i = 0; i < p.size();) {
    if (p[i] != '$') {
      out += p[i++];
      continue;
    }
    const bool braced = i + 1 < p.size() && p[i + 1] == '{';
    std::size_t j = i + (braced ? 2 : 1), start = j;
    while (j < p.size() && (std::isalnum(static_cast<unsigned char>(p[j])) || p[j] == '_')) ++j;
    const bool closed = !braced || (j < p.size() && p[j] == '}');
    const std::string name = p.substr(start, j - start);
    const char* value = name.empty() || !closed ? nullptr : std::getenv(name.c_str());
    if (!value) {  // left as written
      out += p[i++];
      continue;
    }
    out += value;
    i = braced ? j + 1 : j;
  }
  return out;
}

std::string hf_home() {
  std::string home = env("HF_HOME");
  if (home.empty()) {
    const std::string xdg = env("XDG_CACHE_HOME");
    home = (xdg.empty() ? "~/.cache" : xdg) + "/huggingface";
  }
  return expand_user_and_vars(home);
}

std::string hf_hub_cache() {
  for (const char* name : {"HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"})
    if (std::string v = env(name); !v.empty()) return expand_user_and_vars(v);
  return hf_home() + "/hub";
}

}  // namespace tether
