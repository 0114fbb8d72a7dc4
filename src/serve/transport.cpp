// The transports a server runs besides HTTP, chosen by the options.
#include "serve/transport.h"

namespace tether::serve {

std::vector<std::unique_ptr<Transport>> make_transports(const TransportContext& ctx) {
  std::vector<std::unique_ptr<Transport>> transports;
  (void)ctx;
  return transports;
}

}  // namespace tether::serve
