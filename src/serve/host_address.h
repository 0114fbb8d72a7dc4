// What --host names, as addresses to bind: an IP address as it is, a host name ("localhost") through getaddrinfo.
// HTTP and openpi bind the first address; the ZMQ transports every one (libzmq binds numeric addresses only).
#pragma once

#include <string>
#include <vector>

namespace tether::serve {

// The numeric addresses of `host` in getaddrinfo's order, without repeats: one for an IP address, one or more for a
// name. Throws tether::Error(invalid_argument) naming the host when it is neither an address nor a name that
// resolves (the CLI exits 2 with that line).
std::vector<std::string> resolve_host(const std::string& host);

}  // namespace tether::serve
