// The breaker's state machine with an explicit clock: closed -> open after N failures, refusals while open, one
// half-open probe after the reset time, and the probe's outcome closing or re-opening the circuit.
#include <gtest/gtest.h>

#include "runtime/circuit_breaker.h"

using namespace tether::runtime;
using namespace std::chrono_literals;
using Admission = CircuitBreaker::Admission;
using State = CircuitBreaker::State;

TEST(CircuitBreaker, DisabledAlwaysAdmits) {
  CircuitBreaker b(0, 60s);
  EXPECT_FALSE(b.enabled());
  for (int i = 0; i < 10; ++i) b.record_failure();
  EXPECT_EQ(b.admit(), Admission::run);
  EXPECT_EQ(b.state(), State::closed);
  EXPECT_EQ(b.consecutive_failures(), 10);
}

TEST(CircuitBreaker, OpensAfterConsecutiveFailuresOnly) {
  const auto t0 = CircuitBreaker::Clock::now();
  CircuitBreaker b(3, 60s);
  b.record_failure(t0);
  b.record_failure(t0);
  b.record_success();  // the run of failures is broken
  b.record_failure(t0);
  b.record_failure(t0);
  EXPECT_EQ(b.state(t0), State::closed);
  EXPECT_EQ(b.admit(t0), Admission::run);
  b.record_failure(t0);
  EXPECT_EQ(b.state(t0), State::open);
  EXPECT_EQ(b.times_opened(), 1u);
  EXPECT_EQ(b.admit(t0 + 59s), Admission::reject);
  EXPECT_EQ(b.retry_after_s(t0), 60);
  EXPECT_EQ(b.retry_after_s(t0 + 59500ms), 1);
}

TEST(CircuitBreaker, OneProbeAtATimeThenCloses) {
  const auto t0 = CircuitBreaker::Clock::now();
  CircuitBreaker b(1, 10s);
  b.record_failure(t0);
  EXPECT_EQ(b.state(t0 + 10s), State::half_open);
  EXPECT_EQ(b.admit(t0 + 10s), Admission::probe);
  EXPECT_EQ(b.admit(t0 + 10s), Admission::reject);  // a second request waits for the probe's outcome
  b.record_success();
  EXPECT_EQ(b.state(t0 + 10s), State::closed);
  EXPECT_EQ(b.consecutive_failures(), 0);
  EXPECT_EQ(b.admit(t0 + 10s), Admission::run);
}

TEST(CircuitBreaker, FailedProbeReopensForAFullPeriod) {
  const auto t0 = CircuitBreaker::Clock::now();
  CircuitBreaker b(2, 10s);
  b.record_failure(t0);
  b.record_failure(t0);
  ASSERT_EQ(b.admit(t0 + 11s), Admission::probe);
  b.record_failure(t0 + 12s);
  EXPECT_EQ(b.state(t0 + 12s), State::open);
  EXPECT_EQ(b.times_opened(), 2u);
  EXPECT_EQ(b.admit(t0 + 21s), Admission::reject);
  EXPECT_EQ(b.admit(t0 + 22s), Admission::probe);
}

TEST(CircuitBreaker, AbandonedProbeLetsAnotherIn) {
  const auto t0 = CircuitBreaker::Clock::now();
  CircuitBreaker b(1, 1s);
  b.record_failure(t0);
  ASSERT_EQ(b.admit(t0 + 2s), Admission::probe);
  b.abandon_probe();
  EXPECT_EQ(b.admit(t0 + 2s), Admission::probe);
}
