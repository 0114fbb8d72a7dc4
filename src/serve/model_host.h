// The served model's life cycle: loaded and warmed up on a background thread while the socket already answers,
// then held (engine, batcher, safety wedges) for every transport, with the health state /health reports.
#pragma once

#include <atomic>
#include <exception>
#include <functional>
#include <memory>

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
  ModelHost(EngineLoader loader, runtime::BatcherOptions batch, runtime::WedgeOptions wedge_options, Metrics& metrics);
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

 private:
  EngineLoader loader_;
  runtime::BatcherOptions batch_options_;
  Metrics& metrics_;
  runtime::Wedges wedges_;
  std::atomic<HealthState> state_{HealthState::loading};
  // Written once by the loader thread before `state_` leaves `loading` (release), read after (acquire).
  std::unique_ptr<Engine> engine_;
  std::unique_ptr<runtime::Batcher> batcher_;
  std::exception_ptr load_error_;
};

// How the engine runs, as /config and every /act response report it.
Json inference_mode_json(const Engine& engine);

}  // namespace tether::serve
