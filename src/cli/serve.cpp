// `tether serve`: the HTTP action server for one checkpoint directory (API: /act, /health, /ready, /live, /config,
// /metrics). Prints one "listening on" line to stdout once bound; everything else goes to stderr.
#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "cli/serve_flags.h"
#include "core/error.h"

namespace tether::cli {

namespace {

std::string read_key_file(const std::string& path, const char* flag) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::not_found, std::string(flag) + " " + path + ": cannot read");
  std::string key((std::istreambuf_iterator<char>(in)), {});
  while (!key.empty() && std::isspace(static_cast<unsigned char>(key.back()))) key.pop_back();
  if (key.empty()) throw Error(ErrorCode::invalid_argument, std::string(flag) + " " + path + ": the file is empty");
  return key;
}

std::string read_api_key(const ServeFlags& flags) {
  if (!flags.api_key_file.empty()) return read_key_file(flags.api_key_file, "--api-key-file");
  const char* env = std::getenv("TETHER_API_KEY");
  return env ? std::string(env) : std::string();
}

}  // namespace

void add_serve_flags(CLI::App* sub, ServeFlags& f) {
  auto& o = f.options;
  sub->add_option("--host", o.host, "Address or host name to listen on (0.0.0.0 for every interface)")
      ->capture_default_str();
  sub->add_option("--port", o.port, "TCP port; 0 picks a free one")->capture_default_str();
  sub->add_option("--api-key-file", f.api_key_file,
                  "File holding the API key /act and /config require (else env TETHER_API_KEY; unset: open)");
  sub->add_option("--max-batch", o.batch.max_batch, "Most requests sharing one forward pass")
      ->capture_default_str()->check(CLI::Range(1, 1024));
  sub->add_option("--batch-timeout-ms", o.batch.batch_timeout_ms, "0: continuous batching (a pass starts as soon as the engine is free); above 0: how long a request waits for others to batch with")
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
  sub->add_option("--model-name", o.model_name,
                  "Name of the model on KServe's /v2/models/{name} (default: the checkpoint directory's name)");
  sub->add_option("--threads", o.threads, "I/O threads (inference has its own)")->capture_default_str()
      ->check(CLI::Range(1, 256));
  add_precision_flag(sub, f.precision);
  add_backend_flag(sub, f.backend);
  sub->add_option("--embodiment-tag", f.embodiment_tags,
                  "Embodiment served, for checkpoints trained on several (GR00T: a tag of its embodiment_id.json). "
                  "Repeat it (or separate tags by commas) to serve several from one copy of the weights: the first "
                  "is the default, a request picks another by its tag. Default: the checkpoint's only one")
      ->delimiter(',');

  // Safety wedges (off unless given; order and semantics in the README).
  auto& w = o.wedges;
  const std::string wedges = "Safety wedges";
  const std::string per_tag = " (TAG=... for one of several --embodiment-tag robots; repeatable)";
  sub->add_option("--embodiment", f.embodiment,
                  "Embodiment preset: franka, so100, ur5, quadcopter (joint limits, rate)" + per_tag)
      ->group(wedges);
  sub->add_option("--custom-embodiment-config", f.custom_embodiment,
                  "Embodiment JSON file (same format as the presets)" + per_tag)
      ->group(wedges);
  sub->add_option("--safety-config", f.safety_config,
                  "Joint limits JSON (ros2_control JointLimits fields); overrides the embodiment's per joint" + per_tag)
      ->group(wedges);
  sub->add_option("--audit-log", w.audit_log,
                  "JSON-lines file every guard clamp is appended to (default: audit.jsonl in --record DIR, else "
                  "./tether-audit.jsonl)")
      ->group(wedges);
  sub->add_option("--control-rate-hz", w.control_rate_hz,
                  "Control rate for elapsed-step arithmetic (default: the embodiment's, else 30)")
      ->group(wedges)->check(CLI::Range(0.0, 100000.0));
  sub->add_option("--deadline-ms", w.deadline_ms,
                  "Answer by this time after receipt; a late model is replaced by the last good chunk")
      ->group(wedges)->check(CLI::Range(0.0, 3600000.0));
  sub->add_flag("--adaptive-steps", f.adaptive_steps, "Stop denoising once the velocity stops changing")->group(wedges);
  sub->add_option("--adaptive-threshold", f.adaptive_threshold,
                  "Relative velocity change under which --adaptive-steps stops (default 0.05; implies --adaptive-steps)")
      ->group(wedges)->check(CLI::Range(0.0, 10.0));
  sub->add_option("--action-similarity-threshold", w.similarity_threshold,
                  "Reuse the cached chunk when the observation moved less than this (see README)")
      ->group(wedges)->check(CLI::Range(0.0, 1e9));
  sub->add_option("--max-similar-skips", w.max_similar_skips, "At most this many reuses in a row")
      ->group(wedges)->check(CLI::Range(0, 1000000));
  sub->add_option("--max-consecutive-crashes", w.max_consecutive_crashes,
                  "Open the circuit after this many inference failures in a row (0: never)")
      ->group(wedges)->check(CLI::Range(0, 1000000));
  sub->add_option("--circuit-reset-ms", w.circuit_reset_ms, "How long an open circuit waits before a probe")
      ->group(wedges)->capture_default_str()->check(CLI::Range(1, 86400000));
  sub->add_option("--cloud-fallback", w.cloud_fallback,
                  "URL of another Tether server whose /act answers when local inference fails or is late")
      ->group(wedges);
  sub->add_option("--fallback-timeout-ms", w.fallback_timeout_ms, "Limit on one fallback call")
      ->group(wedges)->capture_default_str()->check(CLI::Range(1, 600000));
  sub->add_option("--fallback-api-key-file", f.fallback_api_key_file,
                  "API key for the fallback server (else env TETHER_FALLBACK_API_KEY)")
      ->group(wedges);
  sub->add_option("--inject-latency-ms", w.inject_latency_ms, "Synthetic delay added to every forward pass (testing)")
      ->group(wedges)->check(CLI::Range(0.0, 600000.0));
  sub->add_option("--inject-failure-file", w.inject_failure_file,
                  "While this file exists every forward pass fails (rehearse the breaker and fallback)")
      ->group(wedges);
  sub->add_flag("--rtc", w.sampler.rtc, "Accept real-time chunking inputs (rtc.prev_actions, rtc.inference_delay)")
      ->group(wedges);
  sub->add_option("--rtc-execution-horizon", w.sampler.rtc_execution_horizon, "RTC: steps of the leftover that guide")
      ->group(wedges)->capture_default_str()->check(CLI::Range(1, 100000));
  sub->add_option("--rtc-max-guidance-weight", w.sampler.rtc_max_guidance_weight, "RTC: cap on the guidance weight")
      ->group(wedges)->capture_default_str()->check(CLI::Range(0.0, 1e6));
  sub->add_option("--rtc-schedule", f.rtc_schedule, "RTC prefix weights: linear, exp, ones, zeros")
      ->group(wedges)->capture_default_str()->check(CLI::IsMember({"linear", "exp", "ones", "zeros"}));
  sub->add_option("--record", f.record_dir, "Append every /act request and response to hash-chained JSONL traces here")
      ->group(wedges);
  sub->add_option("--record-max-bytes", f.record_max_bytes, "Rotate trace files at this size")
      ->group(wedges)->capture_default_str()->check(CLI::Range(std::uint64_t(4096), std::uint64_t(1) << 40));
  sub->add_option("--record-images", f.record_images, "hash (sha256 of the pixels) or full (the pixels, replayable)")
      ->group(wedges)->capture_default_str()->check(CLI::IsMember({"hash", "full"}));
  sub->add_option("--record-fsync", f.record_fsync, "every_line, interval (each second) or never")
      ->group(wedges)->capture_default_str()->check(CLI::IsMember({"every_line", "interval", "never"}));
  sub->add_option("--max-episodes", w.max_episodes, "Episodes kept in memory (least recently used forgotten)")
      ->group(wedges)->capture_default_str()->check(CLI::Range(std::size_t(1), std::size_t(1) << 24));
  // GR00T's and Tether's ZMQ transports (docs/transports/gr00t.md, zmq.md).
  const char* zmq_group = "ZMQ transports";
  sub->add_option("--gr00t-port", o.gr00t_port, "Serve Isaac-GR00T's ZMQ PolicyClient protocol on this port (0: a free one)")
      ->group(zmq_group);
  sub->add_option("--gr00t-max-message-bytes", o.gr00t_max_message_bytes, "Larger GR00T messages: the peer is dropped")
      ->group(zmq_group)->capture_default_str();
  sub->add_flag("--gr00t-allow-kill", o.gr00t_allow_kill, "GR00T's kill endpoint shuts the server down (else refused)")
      ->group(zmq_group);
  sub->add_option("--zmq-port", o.zmq_port, "Serve Tether's ZMQ protocol (ROUTER) on this port (0: a free one)")
      ->group(zmq_group);
  sub->add_option("--zmq-max-message-bytes", o.zmq_max_message_bytes, "Larger Tether ZMQ messages: the peer is dropped")
      ->group(zmq_group)->capture_default_str();
  sub->add_option("--zmq-curve-secret-file", o.zmq_curve_secret_file,
                  "Z85 CURVE secret key: the --zmq-port is encrypted (clients need the public key it prints)")
      ->group(zmq_group);
  add_openpi_flags(sub, f);
}


std::string embodiment_preset_file(const std::string& name) {
  const std::string dir = data_file("embodiments");
  policy::load_embodiment_preset(name, dir);
  return (std::filesystem::path(dir) / (name + ".json")).string();
}

namespace {

// One robot-side flag's value for the embodiment `tag`: its TAG=VALUE entry, else the entry for every embodiment.
struct RobotValue {
  std::string value;  // empty: none
  bool own = false;   // from a TAG=VALUE entry
};

RobotValue robot_value(const std::vector<std::string>& entries, const std::vector<std::string>& tags,
                       const std::string& tag, const char* flag, bool is_file) {
  const PerEmbodiment values = per_embodiment(entries, tags, flag, is_file);
  if (const auto own = values.own.find(tag); own != values.own.end()) return {own->second, true};
  return {values.shared, false};
}

}  // namespace

PerEmbodiment per_embodiment(const std::vector<std::string>& entries, const std::vector<std::string>& tags,
                             const char* flag, bool is_file) {
  PerEmbodiment out;
  bool shared_given = false;
  for (const std::string& entry : entries) {
    const std::size_t eq = entry.find('=');
    const std::string prefix = eq == std::string::npos ? "" : entry.substr(0, eq);
    const bool tagged = !prefix.empty() && std::find(tags.begin(), tags.end(), prefix) != tags.end();
    // An apparent TAG= naming neither a served tag nor a file is a mistyped tag, not a value.
    if (!tagged && !prefix.empty() && !tags.empty() && !(is_file && std::filesystem::exists(entry))) {
      std::string served;
      for (const auto& t : tags) served += (served.empty() ? "" : ", ") + t;
      throw Error(ErrorCode::invalid_argument, std::string(flag) + " " + entry + ": '" + prefix +
                                                   "' is not an embodiment served (--embodiment-tag: " + served + ")" +
                                                   (is_file ? ", and no file '" + entry + "' exists" : ""));
    }
    const bool twice = tagged ? out.own.count(prefix) > 0 : shared_given;
    if (twice)
      throw Error(ErrorCode::invalid_argument, std::string(flag) + " is given twice for " +
                                                   (tagged ? "embodiment '" + prefix + "'" : std::string("every embodiment")));
    if (tagged) out.own[prefix] = entry.substr(eq + 1);
    else out.shared = entry, shared_given = true;
  }
  return out;
}

runtime::WedgeOptions wedge_options(const ServeFlags& f, const std::string& checkpoint_dir, const std::string& tag) {
  runtime::WedgeOptions w = f.options.wedges;
  const auto& tags = f.embodiment_tags;
  const RobotValue preset = robot_value(f.embodiment, tags, tag, "--embodiment", false);
  const RobotValue custom = robot_value(f.custom_embodiment, tags, tag, "--custom-embodiment-config", true);
  const RobotValue safety = robot_value(f.safety_config, tags, tag, "--safety-config", true);
  // The embodiment's own entry wins over a shared one of the other flag; two at one level are ambiguous.
  if (!preset.value.empty() && !custom.value.empty() && preset.own == custom.own)
    throw Error(ErrorCode::invalid_argument, "give --embodiment or --custom-embodiment-config, not both" +
                                                 (tag.empty() ? std::string() : " (embodiment '" + tag + "')"));
  const bool use_custom = !custom.value.empty() && (preset.value.empty() || custom.own);
  if (use_custom) w.embodiment = policy::load_embodiment_file(custom.value);
  else if (!preset.value.empty()) w.embodiment = policy::load_embodiment_preset(preset.value, data_file("embodiments"));
  const auto carried = std::filesystem::path(checkpoint_dir) / kExportEmbodimentFile;
  if (!w.embodiment && std::filesystem::is_regular_file(carried)) {
    w.embodiment = policy::load_embodiment_file(carried.string());
    std::fprintf(stderr, "tether serve: embodiment '%s' from %s\n", w.embodiment->name.c_str(), carried.c_str());
  }
  if (!safety.value.empty()) w.safety = policy::load_safety_config(safety.value);
  // --adaptive-threshold on its own also turns the wedge on.
  const bool adaptive = f.adaptive_steps || f.adaptive_threshold >= 0;
  w.sampler.adaptive_threshold = !adaptive ? 0.0f : f.adaptive_threshold >= 0 ? f.adaptive_threshold : kDefaultAdaptiveThreshold;
  if ((w.similarity_threshold > 0) != (w.max_similar_skips > 0))
    throw Error(ErrorCode::invalid_argument,
                "--action-similarity-threshold and --max-similar-skips work together: give both (> 0)");
  if (!w.cloud_fallback.empty()) {
    if (w.cloud_fallback.rfind("http://", 0) != 0 && w.cloud_fallback.rfind("https://", 0) != 0)
      throw Error(ErrorCode::invalid_argument, "--cloud-fallback " + w.cloud_fallback + ": expected an http:// or https:// URL");
    if (!f.fallback_api_key_file.empty()) w.fallback_api_key = read_key_file(f.fallback_api_key_file, "--fallback-api-key-file");
    else if (const char* env = std::getenv("TETHER_FALLBACK_API_KEY")) w.fallback_api_key = env;
  }
  w.sampler.rtc_schedule = models::parse_rtc_schedule(f.rtc_schedule, "--rtc-schedule");
  if (!f.record_dir.empty()) {
    runtime::TraceOptions t;
    t.dir = f.record_dir;
    t.max_file_bytes = f.record_max_bytes;
    t.fsync = f.record_fsync == "every_line" ? runtime::TraceOptions::Fsync::every_line
              : f.record_fsync == "never" ? runtime::TraceOptions::Fsync::never
                                          : runtime::TraceOptions::Fsync::interval;
    w.record = t;
    w.record_images_full = f.record_images == "full";
  }
  if (w.audit_log.empty() && (w.embodiment || w.safety))
    w.audit_log = f.record_dir.empty() ? "tether-audit.jsonl"
                                       : (std::filesystem::path(f.record_dir) / "audit.jsonl").string();
  return w;
}

int run_server(const std::string& checkpoint_dir, const ServeFlags& flags) {
  // A missing directory is a usage error worth reporting before the socket is bound, not after.
  if (!std::filesystem::is_directory(checkpoint_dir))
    throw Error(ErrorCode::not_found, checkpoint_dir + ": not a checkpoint directory");
  serve::ServerOptions options = flags.options;
  options.api_key = read_api_key(flags);
  std::vector<serve::HostLoader> hosts;
  for (const std::string& tag : flags.embodiment_tags.empty() ? std::vector<std::string>{""} : flags.embodiment_tags) {
    const models::LoadOptions load = load_options(flags.precision, tag, flags.backend);
    // Each robot's own embodiment and safety files (TAG=... entries), else the shared ones.
    hosts.push_back({tag, [checkpoint_dir, load] { return serve::load_policy_engine(checkpoint_dir, load); },
                     wedge_options(flags, checkpoint_dir, tag)});
  }
  // The server's own wedge options (fallback, sampler, traces) are every host's; the default host's stand for them.
  options.wedges = *hosts.front().wedges;
  const PerEmbodiment layouts = per_embodiment(flags.openpi_layouts, flags.embodiment_tags, "--openpi-layout", true);
  if (!layouts.shared.empty()) options.openpi.layout = layouts.shared;
  options.openpi.layout_by_embodiment = layouts.own;
  if (options.model_name.empty()) options.model_name = serve::checkpoint_name(checkpoint_dir);
  serve::Server server(options, std::move(hosts));
  const uint16_t port = server.start();
  // The other transports first: the HTTP line, which clients and scripts wait for, means everything is bound.
  for (const auto& [name, transport_port] : server.transport_ports())
    std::printf("tether serve: %s listening on %s:%u\n", name.c_str(), options.host.c_str(), unsigned(transport_port));
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
