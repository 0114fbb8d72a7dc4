// `tether serve`: the HTTP action server for one checkpoint directory (API: /act, /health, /ready, /live, /config,
// /metrics). Prints one "listening on" line to stdout once bound; everything else goes to stderr.
#include <cctype>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "cli/serve_flags.h"
#include "core/error.h"

namespace tether::cli {

namespace {

std::string read_api_key(const ServeFlags& flags) {
  if (!flags.api_key_file.empty()) {
    std::ifstream in(flags.api_key_file, std::ios::binary);
    if (!in) throw Error(ErrorCode::not_found, "--api-key-file " + flags.api_key_file + ": cannot read");
    std::string key((std::istreambuf_iterator<char>(in)), {});
    while (!key.empty() && std::isspace(static_cast<unsigned char>(key.back()))) key.pop_back();
    if (key.empty()) throw Error(ErrorCode::invalid_argument, "--api-key-file " + flags.api_key_file + ": the file is empty");
    return key;
  }
  const char* env = std::getenv("TETHER_API_KEY");
  return env ? std::string(env) : std::string();
}

}  // namespace

void add_serve_flags(CLI::App* sub, ServeFlags& f) {
  auto& o = f.options;
  sub->add_option("--host", o.host, "Address to listen on (0.0.0.0 for every interface)")->capture_default_str();
  sub->add_option("--port", o.port, "TCP port; 0 picks a free one")->capture_default_str();
  sub->add_option("--api-key-file", f.api_key_file,
                  "File holding the API key /act and /config require (else env TETHER_API_KEY; unset: open)");
  sub->add_option("--max-batch", o.batch.max_batch, "Most requests sharing one forward pass")
      ->capture_default_str()->check(CLI::Range(1, 1024));
  sub->add_option("--batch-timeout-ms", o.batch.batch_timeout_ms, "How long a request waits for others to batch with")
      ->capture_default_str()->check(CLI::Range(0.0, 10000.0));
  sub->add_option("--max-queue", o.batch.max_queue, "Requests waiting beyond this: 503 queue_full")
      ->capture_default_str()->check(CLI::Range(1, 1000000));
  sub->add_option("--max-body-bytes", o.max_body_bytes, "Larger request bodies: 413")->capture_default_str()
      ->check(CLI::Range(std::size_t(1024), std::size_t(1) << 32));
  sub->add_option("--max-header-bytes", o.max_header_bytes, "Larger request headers: 431")->capture_default_str()
      ->check(CLI::Range(std::size_t(256), std::size_t(1) << 24));
  sub->add_option("--read-timeout-ms", o.read_timeout_ms, "Reading a request (and keep-alive idle) limit")
      ->capture_default_str()->check(CLI::Range(1, 3600000));
  sub->add_option("--write-timeout-ms", o.write_timeout_ms, "Writing a response limit")->capture_default_str()
      ->check(CLI::Range(1, 3600000));
  sub->add_option("--request-timeout-ms", o.request_timeout_ms, "A request still queued after this: 408")
      ->capture_default_str()->check(CLI::Range(1, 3600000));
  sub->add_option("--shutdown-timeout-ms", o.shutdown_timeout_ms, "In-flight requests get this long after SIGTERM")
      ->capture_default_str()->check(CLI::Range(0, 3600000));
  sub->add_option("--threads", o.threads, "I/O threads (inference has its own)")->capture_default_str()
      ->check(CLI::Range(1, 256));
  add_precision_flag(sub, f.precision);
}

int run_server(const std::string& checkpoint_dir, const ServeFlags& flags) {
  // A missing directory is a usage error worth reporting before the socket is bound, not after.
  if (!std::filesystem::is_directory(checkpoint_dir))
    throw Error(ErrorCode::not_found, checkpoint_dir + ": not a checkpoint directory");
  serve::ServerOptions options = flags.options;
  options.api_key = read_api_key(flags);
  const models::LoadOptions load = load_options(flags.precision);
  serve::Server server(options, [checkpoint_dir, load] { return serve::load_policy_engine(checkpoint_dir, load); });
  const uint16_t port = server.start();
  std::printf("tether serve: listening on http://%s:%u\n", options.host.c_str(), unsigned(port));
  std::fflush(stdout);
  std::fprintf(stderr, "tether serve: loading %s (%s)\n", checkpoint_dir.c_str(),
               options.api_key.empty() ? "no API key: /act and /config are open" : "API key required for /act and /config");
  server.run();
  std::fprintf(stderr, "tether serve: stopped\n");
  return kExitOk;
}

Verb add_serve(CLI::App& app) {
  struct Args {
    std::string checkpoint;
    ServeFlags flags;
  };
  auto args = std::make_shared<Args>();
  CLI::App* sub = app.add_subcommand("serve", "Serve a checkpoint over HTTP (POST /act, GET /health, /config, /metrics)");
  sub->add_option("checkpoint", args->checkpoint, "Checkpoint directory (LeRobot layout)")->required();
  add_serve_flags(sub, args->flags);
  return {sub, [args] { return run_server(args->checkpoint, args->flags); }};
}

}  // namespace tether::cli
