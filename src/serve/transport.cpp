// The transports a server runs besides HTTP, chosen by the options.
#include "serve/transport.h"

#include "serve/gr00t_transport.h"
#include "serve/zmq_transport.h"
#include "serve/openpi_transport.h"

namespace tether::serve {

std::vector<std::unique_ptr<Transport>> make_transports(const TransportContext& ctx) {
  std::vector<std::unique_ptr<Transport>> transports;
  if (ctx.options.gr00t_port) transports.push_back(make_gr00t_transport(ctx));
  if (ctx.options.zmq_port) transports.push_back(make_zmq_transport(ctx));
  if (ctx.options.openpi_port) transports.push_back(std::make_unique<OpenpiTransport>(ctx));
  return transports;
}

}  // namespace tether::serve
