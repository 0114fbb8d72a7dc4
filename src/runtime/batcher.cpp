// The batching worker: wait for a first request, take everything queued (up to max_batch; with an explicit window,
// first gather until it closes or the batch is full), run one forward pass, hand each request its row.
#include "runtime/batcher.h"

#include <algorithm>

namespace tether::runtime {

namespace {

double ms_between(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

// Completions belong to the caller; one that throws must not take the worker (and every later request) down.
void complete(const Completion& done, std::exception_ptr error, BatchResult result) {
  try {
    done(std::move(error), std::move(result));
  } catch (...) {
  }
}

}  // namespace

ErrorCode BatchError::batch_error_code(Kind kind) {
  switch (kind) {
    case Kind::queue_full:
    case Kind::stopped: return ErrorCode::unavailable;
    case Kind::deadline_exceeded: return ErrorCode::timeout;
    case Kind::inference_failed: return ErrorCode::internal;
  }
  return ErrorCode::internal;
}

Batcher::Batcher(PredictFn predict, BatcherOptions options) : predict_(std::move(predict)), options_(options) {
  options_.max_batch = std::max(1, options_.max_batch);
  options_.max_queue = std::max(1, options_.max_queue);
  options_.batch_timeout_ms = std::max(0.0, options_.batch_timeout_ms);
  worker_ = std::thread([this] { run(); });
}

Batcher::~Batcher() { stop(); }

void Batcher::submit(policy::Observation obs, Clock::time_point deadline, Completion done) {
  const auto now = Clock::now();
  {
    std::lock_guard lock(mu_);
    if (stopping_) throw BatchError(BatchError::Kind::stopped, "the server is shutting down");
    if (int(queue_.size()) >= options_.max_queue)
      throw BatchError(BatchError::Kind::queue_full,
                       "the request queue is full (" + std::to_string(options_.max_queue) + " waiting); retry shortly");
    queue_.push_back(Pending{std::move(obs), now, deadline, std::move(done)});
  }
  cv_.notify_all();
}

std::future<BatchResult> Batcher::submit(policy::Observation obs, Clock::time_point deadline) {
  auto promise = std::make_shared<std::promise<BatchResult>>();
  auto future = promise->get_future();
  submit(std::move(obs), deadline, [promise](std::exception_ptr error, BatchResult result) {
    if (error)
      promise->set_exception(error);
    else
      promise->set_value(std::move(result));
  });
  return future;
}

void Batcher::stop() {
  {
    std::lock_guard lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (worker_.joinable() && worker_.get_id() != std::this_thread::get_id()) worker_.join();
}

int Batcher::queue_depth() const {
  std::lock_guard lock(mu_);
  return int(queue_.size());
}

uint64_t Batcher::batches_run() const {
  std::lock_guard lock(mu_);
  return batches_;
}

uint64_t Batcher::items_run() const {
  std::lock_guard lock(mu_);
  return items_;
}

int Batcher::consecutive_failures() const {
  std::lock_guard lock(mu_);
  return consecutive_failures_;
}

void Batcher::run() {
  const auto window = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double, std::milli>(options_.batch_timeout_ms));
  for (;;) {
    std::vector<Pending> batch;
    {
      std::unique_lock lock(mu_);
      cv_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
      if (queue_.empty()) return;  // stopping, and everything queued has run
      // Continuous batching (no window): start now with whatever is queued, so a lone request on an idle worker
      // runs at once and the requests that arrived during the previous pass share this one. An explicit window opens
      // when the oldest waiting request arrived, so a request that queued behind a long forward pass does not wait
      // again. While stopping, run what is there without waiting for company.
      if (window > Clock::duration::zero()) {
        const auto close_at = queue_.front().enqueued + window;
        cv_.wait_until(lock, close_at,
                       [&] { return stopping_ || int(queue_.size()) >= options_.max_batch; });
      }
      const std::size_t n = std::min(queue_.size(), std::size_t(options_.max_batch));
      batch.reserve(n);
      for (std::size_t i = 0; i < n; ++i) {
        batch.push_back(std::move(queue_.front()));
        queue_.pop_front();
      }
    }
    run_batch(batch);
  }
}

void Batcher::run_batch(std::vector<Pending>& pending) {
  const auto start = Clock::now();
  std::vector<Pending> live;
  live.reserve(pending.size());
  for (auto& p : pending) {
    if (p.deadline <= start) {
      complete(p.done,
               std::make_exception_ptr(BatchError(BatchError::Kind::deadline_exceeded,
                                                  "the request's deadline passed after " +
                                                      std::to_string(int64_t(ms_between(p.enqueued, start))) +
                                                      " ms in the queue")),
               {});
    } else {
      live.push_back(std::move(p));
    }
  }
  if (live.empty()) return;

  std::vector<policy::Observation> observations;
  observations.reserve(live.size());
  for (auto& p : live) observations.push_back(std::move(p.obs));

  policy::Prediction prediction;
  bool failed = false;
  std::string failure;
  try {
    prediction = predict_(observations);
    if (prediction.items.size() != live.size())
      throw Error(ErrorCode::internal, "the policy returned " + std::to_string(prediction.items.size()) +
                                           " results for a batch of " + std::to_string(live.size()));
  } catch (const std::exception& e) {
    failed = true;
    failure = std::string("inference failed: ") + e.what();
  } catch (...) {
    failed = true;
    failure = "inference failed";
  }
  {
    std::lock_guard lock(mu_);
    ++batches_;
    items_ += live.size();
    consecutive_failures_ = failed ? consecutive_failures_ + 1 : 0;
  }
  for (std::size_t i = 0; i < live.size(); ++i) {
    if (failed) {
      // One exception object per request: each is rethrown and destroyed on its own caller's thread.
      complete(live[i].done, std::make_exception_ptr(BatchError(BatchError::Kind::inference_failed, failure)), {});
      continue;
    }
    BatchResult r;
    r.chunk = std::move(prediction.items[i]);
    r.timings = prediction.timings;
    r.normalize_ms = prediction.normalize_ms;
    r.postprocess_ms = prediction.postprocess_ms;
    r.predict_ms = prediction.total_ms;
    r.queue_ms = ms_between(live[i].enqueued, start);
    r.batch_size = int(live.size());
    r.index_in_batch = int(i);
    complete(live[i].done, nullptr, std::move(r));
  }
}

}  // namespace tether::runtime
