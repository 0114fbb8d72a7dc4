// Batching scheduler with a fake predict: a lone request starts a pass at once, requests arriving during a pass share
// the next one, an explicit window gathers, each request gets its own row back, the queue bound, a throwing predict,
// deadlines and draining on stop. Behaviour only: no assertion depends on how long anything took.
#include <gtest/gtest.h>

#include <atomic>
#include <latch>
#include <limits>

#include "runtime/batcher.h"

using namespace tether;
using namespace tether::runtime;
using namespace std::chrono_literals;

namespace {

// A deterministic "model": each item's actions depend only on its own state and seed, like the real engine's
// per-item noise. Records the size of every batch it ran.
struct FakeModel {
  std::mutex mu;
  std::vector<int> batch_sizes;
  std::chrono::milliseconds delay{0};
  std::atomic<bool> fail{false};
  std::atomic<int> concurrent{0}, max_concurrent{0};

  static std::vector<float> expected(const policy::Observation& o) {
    std::vector<float> a(4);
    for (int i = 0; i < 4; ++i) a[i] = o.state.at(0) * float(i + 1) + float(o.seed % 1000) * 0.5f;
    return a;
  }

  policy::Prediction operator()(const std::vector<policy::Observation>& batch) {
    const int now = ++concurrent;
    int prev = max_concurrent.load();
    while (now > prev && !max_concurrent.compare_exchange_weak(prev, now)) {
    }
    {
      std::lock_guard lock(mu);
      batch_sizes.push_back(int(batch.size()));
    }
    if (delay.count() > 0) std::this_thread::sleep_for(delay);
    --concurrent;
    if (fail) throw Error(ErrorCode::internal, "fake model exploded");
    policy::Prediction p;
    for (const auto& o : batch) {
      policy::ActionChunk c;
      c.chunk_size = 2;
      c.action_dim = 2;
      c.actions = expected(o);
      p.items.push_back(std::move(c));
    }
    p.total_ms = 1.0;
    return p;
  }
};

policy::Observation obs(float x, uint64_t seed) {
  policy::Observation o;
  o.state = {x};
  o.seed = seed;
  return o;
}

PredictFn wrap(FakeModel& m) {
  return [&m](const std::vector<policy::Observation>& b) { return m(b); };
}

// A fake model whose forward passes block until the test releases them, so a test can see exactly which requests
// were queued when each pass started, whatever the machine's speed.
struct GatedModel {
  std::mutex mu;
  std::condition_variable cv;
  std::vector<int> batch_sizes;
  int entered = 0, released = 0;

  policy::Prediction operator()(const std::vector<policy::Observation>& batch) {
    std::unique_lock lock(mu);
    batch_sizes.push_back(int(batch.size()));
    const int pass = ++entered;
    cv.notify_all();
    cv.wait(lock, [&] { return released >= pass; });
    policy::Prediction p;
    for (const auto& o : batch) {
      policy::ActionChunk c;
      c.chunk_size = 2;
      c.action_dim = 2;
      c.actions = FakeModel::expected(o);
      p.items.push_back(std::move(c));
    }
    return p;
  }
  // Blocks until `passes` forward passes have started; returns the batch sizes so far.
  std::vector<int> wait_for_passes(int passes) {
    std::unique_lock lock(mu);
    cv.wait(lock, [&] { return entered >= passes; });
    return batch_sizes;
  }
  // Lets the first `passes` forward passes finish (and every later one, with a large count).
  void release(int passes) {
    {
      std::lock_guard lock(mu);
      released = passes;
    }
    cv.notify_all();
  }
  void release_all() { release(std::numeric_limits<int>::max()); }
};

PredictFn wrap(GatedModel& m) {
  return [&m](const std::vector<policy::Observation>& b) { return m(b); };
}

Clock::time_point far() { return Clock::now() + 60s; }

}  // namespace

constexpr double kHourMs = 3600e3;  // an explicit window that never closes within a test

TEST(Batcher, DefaultIsContinuousBatching) { EXPECT_EQ(BatcherOptions{}.batch_timeout_ms, 0.0); }

TEST(Batcher, LoneRequestOnAnIdleWorkerStartsAPassAtOnce) {
  GatedModel model;
  Batcher batcher(wrap(model), {.max_batch = 8, .max_queue = 64});
  auto lone = batcher.submit(obs(1, 1), far());
  // The pass has started with the lone request although no second request has arrived (nor ever will).
  EXPECT_EQ(model.wait_for_passes(1), std::vector<int>({1}));
  EXPECT_EQ(batcher.queue_depth(), 0);
  model.release_all();
  const BatchResult r = lone.get();
  EXPECT_EQ(r.batch_size, 1);
  EXPECT_EQ(r.chunk.actions, FakeModel::expected(obs(1, 1)));
}

TEST(Batcher, RequestsArrivingDuringAPassShareTheNextOne) {
  GatedModel model;
  Batcher batcher(wrap(model), {.max_batch = 8, .max_queue = 64});
  auto first = batcher.submit(obs(0, 0), far());
  EXPECT_EQ(model.wait_for_passes(1), std::vector<int>({1}));
  std::vector<std::future<BatchResult>> during;
  for (int i = 1; i <= 3; ++i) during.push_back(batcher.submit(obs(float(i), 10 + i), far()));
  EXPECT_EQ(batcher.queue_depth(), 3);  // they wait while the pass runs
  model.release(1);
  // The next pass takes all three at once.
  EXPECT_EQ(model.wait_for_passes(2), std::vector<int>({1, 3}));
  model.release_all();
  EXPECT_EQ(first.get().batch_size, 1);
  for (int i = 1; i <= 3; ++i) {
    const BatchResult r = during[i - 1].get();
    EXPECT_EQ(r.batch_size, 3);
    EXPECT_EQ(r.index_in_batch, i - 1);
    EXPECT_EQ(r.chunk.actions, FakeModel::expected(obs(float(i), 10 + i))) << "item " << i << " got another's row";
  }
  EXPECT_EQ(batcher.batches_run(), 2u);
  EXPECT_EQ(batcher.items_run(), 4u);
}

TEST(Batcher, MaxBatchSplitsALongQueue) {
  GatedModel model;
  Batcher batcher(wrap(model), {.max_batch = 3, .max_queue = 64});
  std::vector<std::future<BatchResult>> f;
  f.push_back(batcher.submit(obs(0, 0), far()));
  EXPECT_EQ(model.wait_for_passes(1), std::vector<int>({1}));
  for (int i = 1; i < 8; ++i) f.push_back(batcher.submit(obs(float(i), i), far()));
  EXPECT_EQ(batcher.queue_depth(), 7);
  model.release_all();
  for (int i = 0; i < 8; ++i) EXPECT_EQ(f[i].get().chunk.actions, FakeModel::expected(obs(float(i), i)));
  EXPECT_EQ(model.batch_sizes, std::vector<int>({1, 3, 3, 1}));
  EXPECT_EQ(batcher.batches_run(), 4u);
  EXPECT_EQ(batcher.items_run(), 8u);
}

TEST(Batcher, AnExplicitWindowHoldsALoneRequestForCompany) {
  GatedModel model;
  Batcher batcher(wrap(model), {.max_batch = 2, .batch_timeout_ms = kHourMs, .max_queue = 64});
  auto a = batcher.submit(obs(0, 0), far());
  auto b = batcher.submit(obs(1, 1), far());
  // Continuous batching would have started a pass with `a` alone; the window kept it until the batch was full.
  EXPECT_EQ(model.wait_for_passes(1), std::vector<int>({2}));
  model.release_all();
  EXPECT_EQ(a.get().batch_size, 2);
  EXPECT_EQ(b.get().batch_size, 2);
}

TEST(Batcher, StopRunsARequestAnExplicitWindowIsHolding) {
  GatedModel model;
  model.release_all();
  Batcher batcher(wrap(model), {.max_batch = 8, .batch_timeout_ms = kHourMs, .max_queue = 64});
  auto lone = batcher.submit(obs(3, 3), far());
  batcher.stop();
  EXPECT_EQ(lone.get().chunk.actions, FakeModel::expected(obs(3, 3)));
  EXPECT_EQ(model.batch_sizes, std::vector<int>({1}));
}

TEST(Batcher, RequestsArrivingTogetherShareOnePredictCall) {
  FakeModel model;
  Batcher batcher(wrap(model), {.max_batch = 5, .batch_timeout_ms = kHourMs, .max_queue = 64});
  std::vector<std::future<BatchResult>> futures;
  for (int i = 0; i < 5; ++i) futures.push_back(batcher.submit(obs(float(i), 100 + i), far()));
  for (int i = 0; i < 5; ++i) {
    const BatchResult r = futures[i].get();
    EXPECT_EQ(r.batch_size, 5);
    EXPECT_EQ(r.chunk.actions, FakeModel::expected(obs(float(i), 100 + i))) << "item " << i << " got another's row";
    EXPECT_GE(r.queue_ms, 0.0);
  }
  EXPECT_EQ(model.batch_sizes, std::vector<int>({5}));
  EXPECT_EQ(batcher.batches_run(), 1u);
  EXPECT_EQ(batcher.items_run(), 5u);
}

TEST(Batcher, BatchedResultsEqualRunningAlone) {
  FakeModel batched_model, alone_model;
  std::vector<BatchResult> batched, alone;
  {
    Batcher b(wrap(batched_model), {.max_batch = 4, .batch_timeout_ms = kHourMs, .max_queue = 64});
    std::vector<std::future<BatchResult>> f;
    for (int i = 0; i < 4; ++i) f.push_back(b.submit(obs(0.25f * float(i), 7 * i), far()));
    for (auto& x : f) batched.push_back(x.get());
  }
  {
    Batcher b(wrap(alone_model), {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 64});
    for (int i = 0; i < 4; ++i) alone.push_back(b.submit(obs(0.25f * float(i), 7 * i), far()).get());
  }
  EXPECT_EQ(batched_model.batch_sizes, std::vector<int>({4}));
  EXPECT_EQ(alone_model.batch_sizes, std::vector<int>({1, 1, 1, 1}));
  for (int i = 0; i < 4; ++i) EXPECT_EQ(batched[i].chunk.actions, alone[i].chunk.actions);
}

TEST(Batcher, FullQueueFailsImmediately) {
  FakeModel model;
  model.delay = 300ms;
  Batcher batcher(wrap(model), {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 2});
  auto first = batcher.submit(obs(0, 0), far());
  // Wait until the worker has taken the first request, so the next two fill the queue exactly.
  for (int i = 0; i < 200 && batcher.queue_depth() != 0; ++i) std::this_thread::sleep_for(1ms);
  std::this_thread::sleep_for(20ms);
  auto second = batcher.submit(obs(1, 1), far());
  auto third = batcher.submit(obs(2, 2), far());
  EXPECT_EQ(batcher.queue_depth(), 2);
  // The refusal is synchronous: submit throws instead of handing back a future that would wait for space
  // (the first request still holds the worker, so a waiting submit could only have succeeded).
  try {
    batcher.submit(obs(3, 3), far());
    FAIL() << "submit into a full queue succeeded";
  } catch (const BatchError& e) {
    EXPECT_EQ(e.kind(), BatchError::Kind::queue_full);
  }
  EXPECT_EQ(batcher.queue_depth(), 2);
  EXPECT_EQ(first.get().batch_size, 1);
  EXPECT_EQ(second.get().chunk.actions, FakeModel::expected(obs(1, 1)));
  EXPECT_EQ(third.get().chunk.actions, FakeModel::expected(obs(2, 2)));
}

TEST(Batcher, ThrowingPredictFailsTheBatchAndTheWorkerKeepsRunning) {
  FakeModel model;
  model.fail = true;
  Batcher batcher(wrap(model), {.max_batch = 3, .batch_timeout_ms = kHourMs, .max_queue = 64});
  std::vector<std::future<BatchResult>> f;
  for (int i = 0; i < 3; ++i) f.push_back(batcher.submit(obs(float(i), i), far()));
  for (auto& x : f) {
    try {
      x.get();
      FAIL() << "a request of a failed batch got a result";
    } catch (const BatchError& e) {
      EXPECT_EQ(e.kind(), BatchError::Kind::inference_failed);
      EXPECT_NE(std::string(e.what()).find("fake model exploded"), std::string::npos) << e.what();
    }
  }
  EXPECT_EQ(batcher.consecutive_failures(), 1);
  model.fail = false;
  f.clear();
  for (int i = 5; i < 8; ++i) f.push_back(batcher.submit(obs(float(i), i), far()));  // a full batch: no window wait
  for (int i = 5; i < 8; ++i) EXPECT_EQ(f[i - 5].get().chunk.actions, FakeModel::expected(obs(float(i), i)));
  EXPECT_EQ(batcher.consecutive_failures(), 0);
}

TEST(Batcher, ExpiredRequestsSkipTheForwardPass) {
  FakeModel model;
  model.delay = 100ms;
  Batcher batcher(wrap(model), {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 8});
  auto slow = batcher.submit(obs(0, 0), far());
  auto expiring = batcher.submit(obs(1, 1), Clock::now() + 10ms);
  EXPECT_EQ(slow.get().batch_size, 1);
  try {
    expiring.get();
    FAIL() << "an expired request ran";
  } catch (const BatchError& e) {
    EXPECT_EQ(e.kind(), BatchError::Kind::deadline_exceeded);
  }
  EXPECT_EQ(model.batch_sizes.size(), 1u);
}

TEST(Batcher, StopDrainsQueuedWorkAndRefusesNew) {
  FakeModel model;
  model.delay = 30ms;
  Batcher batcher(wrap(model), {.max_batch = 2, .batch_timeout_ms = 0, .max_queue = 64});
  std::vector<std::future<BatchResult>> f;
  for (int i = 0; i < 6; ++i) f.push_back(batcher.submit(obs(float(i), i), far()));
  batcher.stop();
  for (int i = 0; i < 6; ++i) {
    ASSERT_EQ(f[i].wait_for(0s), std::future_status::ready) << "stop() returned before request " << i << " ran";
    EXPECT_EQ(f[i].get().chunk.actions, FakeModel::expected(obs(float(i), i)));
  }
  try {
    batcher.submit(obs(9, 9), far());
    FAIL() << "submit after stop succeeded";
  } catch (const BatchError& e) {
    EXPECT_EQ(e.kind(), BatchError::Kind::stopped);
  }
  batcher.stop();  // idempotent
}

TEST(Batcher, PredictRunsOnOneThreadAtATime) {
  FakeModel model;
  model.delay = 2ms;
  Batcher batcher(wrap(model), {.max_batch = 4, .max_queue = 256});
  std::vector<std::thread> clients;
  std::atomic<int> ok{0};
  std::latch go(8);
  for (int t = 0; t < 8; ++t)
    clients.emplace_back([&, t] {
      go.arrive_and_wait();
      for (int i = 0; i < 10; ++i) {
        const auto o = obs(float(t), uint64_t(t * 100 + i));
        if (batcher.submit(o, far()).get().chunk.actions == FakeModel::expected(o)) ++ok;
      }
    });
  for (auto& c : clients) c.join();
  EXPECT_EQ(ok.load(), 80);
  EXPECT_EQ(model.max_concurrent.load(), 1);
  EXPECT_EQ(batcher.items_run(), 80u);
  EXPECT_LT(batcher.batches_run(), 80u) << "concurrent clients never shared a forward pass";
}

TEST(Batcher, ThrowingCompletionDoesNotKillTheWorker) {
  FakeModel model;
  Batcher batcher(wrap(model), {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 8});
  batcher.submit(obs(0, 0), far(), [](std::exception_ptr, BatchResult) { throw std::runtime_error("caller bug"); });
  EXPECT_EQ(batcher.submit(obs(1, 1), far()).get().chunk.actions, FakeModel::expected(obs(1, 1)));
}

TEST(BatchError, IsATetherErrorWithTheCodeOfItsKind) {
  const std::pair<BatchError::Kind, tether::ErrorCode> kinds[] = {
      {BatchError::Kind::queue_full, tether::ErrorCode::unavailable},
      {BatchError::Kind::stopped, tether::ErrorCode::unavailable},
      {BatchError::Kind::deadline_exceeded, tether::ErrorCode::timeout},
      {BatchError::Kind::inference_failed, tether::ErrorCode::internal}};
  for (const auto& [kind, code] : kinds) {
    try {
      throw BatchError(kind, "why");
    } catch (const tether::Error& e) {
      EXPECT_EQ(e.code(), code);
      EXPECT_STREQ(e.what(), "why");
    }
  }
}
