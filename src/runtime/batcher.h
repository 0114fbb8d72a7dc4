// Continuous-batching scheduler in front of a Policy: an idle worker starts a forward pass as soon as a request
// arrives; requests arriving while a pass runs queue and all go into the next one (up to max_batch). A single worker
// thread owns the policy (Policy::predict is not thread-safe).
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <mutex>
#include <thread>
#include <vector>

#include "core/error.h"
#include "policy/policy.h"

namespace tether::runtime {

using Clock = std::chrono::steady_clock;

struct BatcherOptions {
  int max_batch = 8;              // most observations in one forward pass
  // 0 (continuous batching): a pass starts as soon as the worker is free, with whatever is queued. Above 0: an
  // explicit gathering window; a pass waits until the oldest queued request has waited this long or max_batch are
  // queued, trading a lone request's latency for fuller batches.
  double batch_timeout_ms = 0.0;
  int max_queue = 64;             // requests waiting (not yet in a forward pass); beyond it submit fails at once
};

// Why a request did not get actions. The server maps each kind to a status and a stable error code; as a
// tether::Error it carries the ErrorCode of its kind (see batch_error_code).
class BatchError : public Error {
 public:
  enum class Kind { queue_full, inference_failed, deadline_exceeded, stopped };
  BatchError(Kind kind, const std::string& message) : Error(batch_error_code(kind), message), kind_(kind) {}
  Kind kind() const { return kind_; }
  // queue_full, stopped: unavailable; deadline_exceeded: timeout; inference_failed: internal.
  static ErrorCode batch_error_code(Kind kind);

 private:
  Kind kind_;
};

// One request's share of a batched forward pass.
struct BatchResult {
  policy::ActionChunk chunk;
  models::StageTimings timings;  // of the whole forward pass (shared by every item of the batch)
  double normalize_ms = 0, postprocess_ms = 0, predict_ms = 0;
  double queue_ms = 0;  // submit -> the forward pass started
  int batch_size = 0;   // requests that shared the forward pass
  int index_in_batch = 0;  // this request's row (0: count the batch once in metrics)
};

using PredictFn = std::function<policy::Prediction(const std::vector<policy::Observation>&)>;
// Called on the worker thread with either an error (non-null) or a result. Must not block for long.
using Completion = std::function<void(std::exception_ptr, BatchResult)>;

class Batcher {
 public:
  // `predict` is only ever called from the worker thread, one batch at a time.
  Batcher(PredictFn predict, BatcherOptions options);
  ~Batcher();
  Batcher(const Batcher&) = delete;
  Batcher& operator=(const Batcher&) = delete;

  // Queues one observation. Throws BatchError(queue_full) at once when max_queue requests are already waiting,
  // BatchError(stopped) after stop(). A request whose deadline has passed when its batch forms is completed with
  // BatchError(deadline_exceeded) and does not enter the forward pass.
  void submit(policy::Observation obs, Clock::time_point deadline, Completion done);
  std::future<BatchResult> submit(policy::Observation obs, Clock::time_point deadline);

  // Refuses new work, runs everything already queued, then joins the worker. Idempotent.
  void stop();

  const BatcherOptions& options() const { return options_; }
  int queue_depth() const;
  // Totals since start, for metrics and tests.
  uint64_t batches_run() const;
  uint64_t items_run() const;
  // Consecutive forward passes that threw (0 after any success): the health state's "degraded" signal.
  int consecutive_failures() const;

 private:
  struct Pending {
    policy::Observation obs;
    Clock::time_point enqueued, deadline;
    Completion done;
  };
  void run();
  void run_batch(std::vector<Pending>& batch);

  PredictFn predict_;
  BatcherOptions options_;
  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::deque<Pending> queue_;
  bool stopping_ = false;
  uint64_t batches_ = 0, items_ = 0;
  int consecutive_failures_ = 0;
  std::thread worker_;
};

}  // namespace tether::runtime
