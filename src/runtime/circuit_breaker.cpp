// Circuit breaker state machine; every transition happens under one mutex.
#include "runtime/circuit_breaker.h"

#include <algorithm>

namespace tether::runtime {

const char* circuit_state_name(CircuitBreaker::State s) {
  switch (s) {
    case CircuitBreaker::State::closed: return "closed";
    case CircuitBreaker::State::open: return "open";
    case CircuitBreaker::State::half_open: return "half_open";
  }
  return "unknown";
}

CircuitBreaker::CircuitBreaker(int max_consecutive_failures, std::chrono::milliseconds reset_after)
    : max_failures_(std::max(0, max_consecutive_failures)), reset_after_(reset_after) {}

CircuitBreaker::Admission CircuitBreaker::admit(Clock::time_point now) {
  std::lock_guard lock(mu_);
  if (!open_) return Admission::run;
  if (probing_ || now - opened_at_ < reset_after_) return Admission::reject;
  probing_ = true;
  return Admission::probe;
}

void CircuitBreaker::record_success() {
  std::lock_guard lock(mu_);
  failures_ = 0;
  open_ = probing_ = false;
}

void CircuitBreaker::record_failure(Clock::time_point now) {
  std::lock_guard lock(mu_);
  ++failures_;
  if (max_failures_ == 0) return;
  // A failed probe re-opens for a full period; so does reaching the threshold while closed.
  if (probing_ || (!open_ && failures_ >= max_failures_)) {
    ++opened_total_;
    open_ = true;
    probing_ = false;
    opened_at_ = now;
  }
}

void CircuitBreaker::abandon_probe() {
  std::lock_guard lock(mu_);
  probing_ = false;
}

CircuitBreaker::State CircuitBreaker::state(Clock::time_point now) const {
  std::lock_guard lock(mu_);
  if (!open_) return State::closed;
  return probing_ || now - opened_at_ >= reset_after_ ? State::half_open : State::open;
}

int CircuitBreaker::consecutive_failures() const {
  std::lock_guard lock(mu_);
  return failures_;
}

uint64_t CircuitBreaker::times_opened() const {
  std::lock_guard lock(mu_);
  return opened_total_;
}

int CircuitBreaker::retry_after_s(Clock::time_point now) const {
  std::lock_guard lock(mu_);
  if (!open_) return 0;
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(reset_after_ - (now - opened_at_));
  return std::max<int>(1, int((left.count() + 999) / 1000));
}

}  // namespace tether::runtime
