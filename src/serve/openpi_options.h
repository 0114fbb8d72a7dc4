// The openpi WebSocket transport's switches (`tether serve --openpi-*`); its port is ServerOptions::openpi_port.
#pragma once

#include <cstddef>
#include <map>
#include <string>

namespace tether::serve {

struct OpenpiOptions {
  // How observation keys map onto the checkpoint: auto, libero, droid, aloha or a JSON mapping file
  // (docs/transports/openpi.md).
  std::string layout = "auto";
  // A GR00T server of several embodiments: a robot's own layout by tag (its client's keys), else `layout`.
  std::map<std::string, std::string> layout_by_embodiment;
  std::size_t max_frame_bytes = 0;  // 0: --max-body-bytes; a larger frame closes its connection with 1009
  // A connection waiting for a frame from which nothing (not even a pong to the server's ping at half this) arrives
  // for this long is closed; 0: never. Time spent answering it does not count.
  int idle_timeout_ms = 60000;
};

}  // namespace tether::serve
