// The fault-injection wrappers around a predict function.
#include "runtime/fault_injection.h"

#include <chrono>
#include <filesystem>
#include <thread>

#include "core/error.h"

namespace tether::runtime {

PredictFn with_injected_faults(PredictFn predict, double latency_ms, const std::string& failure_file) {
  if (latency_ms > 0)
    predict = [predict, latency_ms](const std::vector<policy::Observation>& batch) {
      std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(latency_ms));
      return predict(batch);
    };
  // Checked on every call, so a test (or an operator) can break and heal a running server by touching the file.
  if (!failure_file.empty())
    predict = [predict, failure_file](const std::vector<policy::Observation>& batch) {
      if (std::filesystem::exists(failure_file))
        throw Error(ErrorCode::internal, "injected failure (--inject-failure-file " + failure_file + " exists)");
      return predict(batch);
    };
  return predict;
}

}  // namespace tether::runtime
