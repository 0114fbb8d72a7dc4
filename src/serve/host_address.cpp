// Resolving --host with getaddrinfo.
#include "serve/host_address.h"

#include <netdb.h>
#include <sys/socket.h>

#include <algorithm>

#include "core/error.h"

namespace tether::serve {

namespace {

std::vector<std::string> lookup(const std::string& host, int flags) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = flags;
  addrinfo* found = nullptr;
  if (getaddrinfo(host.c_str(), nullptr, &hints, &found) != 0) return {};
  std::vector<std::string> out;
  for (const addrinfo* a = found; a; a = a->ai_next) {
    char text[NI_MAXHOST];
    if (getnameinfo(a->ai_addr, a->ai_addrlen, text, sizeof text, nullptr, 0, NI_NUMERICHOST) != 0) continue;
    if (std::find(out.begin(), out.end(), text) == out.end()) out.emplace_back(text);
  }
  freeaddrinfo(found);
  return out;
}

}  // namespace

std::vector<std::string> resolve_host(const std::string& host) {
  if (host.empty()) throw Error(ErrorCode::invalid_argument, "--host is empty: give an IP address or a host name");
  // Only the families this machine has an address in (a name's IPv6 address on a host without IPv6 would not bind);
  // a machine with nothing but loopback has none by that rule, so then every address the name has.
  std::vector<std::string> addresses = lookup(host, AI_ADDRCONFIG);
  if (addresses.empty()) addresses = lookup(host, 0);
  if (addresses.empty())
    throw Error(ErrorCode::invalid_argument, "--host '" + host + "' is neither an IP address nor a known name");
  return addresses;
}

}  // namespace tether::serve
