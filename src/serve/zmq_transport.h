// `--zmq-port`: Tether's own ZMQ protocol (zmq_protocol.h) on a ROUTER socket, optionally CURVE-encrypted: many robots
// share one port and their requests batch together.
#pragma once

#include <memory>

#include "serve/transport.h"

namespace tether::serve {

std::unique_ptr<Transport> make_zmq_transport(const TransportContext& ctx);

}  // namespace tether::serve
