// Circuit breaker for local inference: after N consecutive failures the circuit opens and requests are refused
// (503 + Retry-After) without touching the model; once the reset time has passed, one request is let through as a
// half-open probe, and its outcome closes the circuit or opens it for another period.
#pragma once

#include <chrono>
#include <cstdint>
#include <mutex>

namespace tether::runtime {

class CircuitBreaker {
 public:
  using Clock = std::chrono::steady_clock;
  enum class State { closed, open, half_open };

  // max_consecutive_failures 0 disables the breaker (allow() always admits).
  CircuitBreaker(int max_consecutive_failures, std::chrono::milliseconds reset_after);

  enum class Admission { run, probe, reject };
  // Whether a request may run inference now. `probe`: this request is the half-open probe; its outcome must be
  // reported with record_success / record_failure (every admitted request's outcome should be).
  Admission admit(Clock::time_point now = Clock::now());
  void record_success();
  void record_failure(Clock::time_point now = Clock::now());
  // A probe that ended without an outcome (e.g. its request was refused before inference): let another probe in.
  void abandon_probe();

  bool enabled() const { return max_failures_ > 0; }
  State state(Clock::time_point now = Clock::now()) const;
  int consecutive_failures() const;
  uint64_t times_opened() const;
  // Whole seconds until a probe is admitted (at least 1 while open; 0 when closed).
  int retry_after_s(Clock::time_point now = Clock::now()) const;
  std::chrono::milliseconds reset_after() const { return reset_after_; }

 private:
  const int max_failures_;
  const std::chrono::milliseconds reset_after_;
  mutable std::mutex mu_;
  int failures_ = 0;
  bool open_ = false, probing_ = false;
  Clock::time_point opened_at_{};
  uint64_t opened_total_ = 0;
};

const char* circuit_state_name(CircuitBreaker::State s);

}  // namespace tether::runtime
