// `--gr00t-port`: Isaac-GR00T's ZMQ PolicyServer protocol (gr00t_protocol.h) on a ROUTER socket, so upstream's
// PolicyClient (a REQ socket) and many of them at once are served, each get_action batch item through the ActPipeline.
#pragma once

#include <memory>

#include "serve/transport.h"

namespace tether::serve {

std::unique_ptr<Transport> make_gr00t_transport(const TransportContext& ctx);

}  // namespace tether::serve
