// The openpi WebSocket transport's flags on `tether serve` and `tether go` (docs/transports/openpi.md).
#include "cli/serve_flags.h"

namespace tether::cli {

void add_openpi_flags(CLI::App* sub, ServeFlags& f) {
  serve::ServerOptions& o = f.options;
  const std::string group = "openpi WebSocket transport";
  sub->add_option("--openpi-port", o.openpi_port,
                  "Also serve openpi's WebSocket policy protocol on this port (0 picks a free one)")
      ->group(group)->check(CLI::Range(0, 65535));
  sub->add_option("--openpi-layout", f.openpi_layouts,
                  "Observation keys: auto (default), libero, droid, aloha, or a JSON mapping file; TAG=... for one of "
                  "several --embodiment-tag robots (repeatable)")
      ->group(group);
  sub->add_option("--openpi-max-frame-bytes", o.openpi.max_frame_bytes,
                  "Larger frames close the connection with 1009 (0: --max-body-bytes)")
      ->group(group)->capture_default_str()->check(CLI::Range(std::size_t(0), std::size_t(1) << 32));
  sub->add_option("--openpi-idle-timeout-ms", o.openpi.idle_timeout_ms,
                  "Close a connection silent this long, pings unanswered (0: never)")
      ->group(group)->capture_default_str()->check(CLI::Range(0, 86400000));
}

}  // namespace tether::cli
