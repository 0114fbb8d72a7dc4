// The served model's life cycle: loaded and warmed up on a background thread while the socket already answers,
// then held (engine, batcher, safety wedges) for every transport, with the health state /health reports.
#pragma once

#include <atomic>
#include <exception>
#include <functional>
#include <memory>
#include <optional>

#include "core/json_util.h"
#include "runtime/batcher.h"
#include "runtime/wedges.h"
#include "serve/engine.h"
#include "serve/metrics.h"

namespace tether::serve {

// The model's life cycle as /health reports it. `degraded`: the warm-up or the last few forward passes failed.
enum class HealthState { loading, warming, ready, degraded, failed, circuit_open };
const char* health_state_name(HealthState s);

using EngineLoader = std::function<Engine()>;

class ModelHost {
 public:
  // Builds the wedges from `wedge_options` at once (a bad audit log or trace directory throws here); the model
  // itself is loaded by load().
  // `embodiment`: the GR00T embodiment tag this host was asked to serve (empty: the checkpoint's only one, or a model
  // without tags).
  // `metric_labels`: what tells this host's wedge metrics apart from other hosts' (see ModelHosts).
  ModelHost(EngineLoader loader, runtime::BatcherOptions batch, runtime::WedgeOptions wedge_options, Metrics& metrics,
            std::string embodiment = "", std::string metric_labels = "");
  ~ModelHost();
  ModelHost(const ModelHost&) = delete;
  ModelHost& operator=(const ModelHost&) = delete;

  // Loads the engine, binds the wedges, starts the batcher and warms up. Meant for a background thread; never
  // throws: returns false (state `failed`, the exception kept for load_error()) when the model could not be loaded.
  bool load();
  // Refuses new work and finishes what the batcher holds. Idempotent; call once the thread running load() has
  // been joined.
  void stop();

  // /health's view: the model's state, overridden by an open circuit.
  HealthState health() const;
  // The model's own state (loading .. degraded), ignoring the circuit.
  HealthState model_state() const;
  // Engine and batcher exist (and are safe to read) once loading has finished successfully.
  bool loaded() const;
  // Ready or degraded: requests may run.
  bool serving() const;

  // Only once loaded().
  const Engine& engine() const { return *engine_; }
  runtime::Batcher& batcher() { return *batcher_; }

  runtime::Wedges& wedges() { return wedges_; }
  const runtime::Wedges& wedges() const { return wedges_; }
  std::exception_ptr load_error() const { return load_error_; }
  // The tag requests name this host by: the one asked for, else (once loaded) the model's own; empty for a model
  // without embodiment tags.
  std::string embodiment() const;
  // Labels (without braces) in front of this host's wedge metric series: `embodiment="TAG"` when the server serves
  // several embodiments, empty otherwise.
  const std::string& metric_labels() const { return metric_labels_; }

 private:
  EngineLoader loader_;
  std::string embodiment_;
  std::string metric_labels_;
  runtime::BatcherOptions batch_options_;
  Metrics& metrics_;
  runtime::Wedges wedges_;
  std::atomic<HealthState> state_{HealthState::loading};
  // Written once by the loader thread before `state_` leaves `loading` (release), read after (acquire).
  std::unique_ptr<Engine> engine_;
  std::unique_ptr<runtime::Batcher> batcher_;
  std::exception_ptr load_error_;
};

// What a server serves: one ModelHost, or one per embodiment of a GR00T checkpoint (`serve --embodiment-tag a
// --embodiment-tag b`), all loaded from one copy of the shared weights (models::load_gr00t_embodiment). The first is
// the default; a request picks another by its tag (ActInput::embodiment). Each host has its own batcher, wedges, last
// good chunks and guard; with several, each records its traces in its own sub-directory of --record (one hash chain
// per embodiment).
struct HostLoader {
  std::string embodiment;  // empty: the default (a single host)
  EngineLoader load;
  // This embodiment's own wedge options (its robot's embodiment and safety files); none: the server's.
  std::optional<runtime::WedgeOptions> wedges = std::nullopt;
};

class ModelHosts {
 public:
  ModelHosts(std::vector<HostLoader> loaders, runtime::BatcherOptions batch, const runtime::WedgeOptions& wedges,
             Metrics& metrics);
  ModelHosts(const ModelHosts&) = delete;
  ModelHosts& operator=(const ModelHosts&) = delete;

  std::size_t size() const { return hosts_.size(); }
  ModelHost& operator[](std::size_t i) { return *hosts_.at(i); }
  const ModelHost& operator[](std::size_t i) const { return *hosts_.at(i); }
  ModelHost& primary() { return *hosts_.front(); }
  const ModelHost& primary() const { return *hosts_.front(); }
  // The host serving `embodiment` (empty: the default). Throws HttpError(400, "unknown_embodiment") listing the tags
  // served.
  ModelHost& route(const std::string& embodiment);
  // The tags requests may name, in host order.
  std::vector<std::string> embodiments() const;

  // Loads every host in order (ModelHost::load); false as soon as one fails (the others are left unloaded).
  bool load();
  void stop();
  // /health's view of them all: the least ready one's state (failed, loading, warming, circuit_open, degraded, ready).
  HealthState health() const;
  // The first host's load error, if one failed.
  std::exception_ptr load_error() const;

 private:
  std::vector<std::unique_ptr<ModelHost>> hosts_;
};

// How the engine runs, as /config and every /act response report it.
Json inference_mode_json(const Engine& engine);

}  // namespace tether::serve
