// Fault injection around a predict function: the delay comes first, the failure file is checked on every call.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>

#include "core/error.h"
#include "runtime/fault_injection.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::runtime;

namespace {

PredictFn counting(int& calls) {
  return [&calls](const std::vector<policy::Observation>& batch) {
    ++calls;
    policy::Prediction p;
    p.items.resize(batch.size());
    return p;
  };
}

}  // namespace

TEST(FaultInjection, NothingSetLeavesPredictAlone) {
  int calls = 0;
  auto predict = with_injected_faults(counting(calls), 0, "");
  EXPECT_EQ(predict(std::vector<policy::Observation>(2)).items.size(), 2u);
  EXPECT_EQ(calls, 1);
}

TEST(FaultInjection, LatencyDelaysEveryCall) {
  int calls = 0;
  auto predict = with_injected_faults(counting(calls), 30, "");
  const auto t0 = std::chrono::steady_clock::now();
  predict(std::vector<policy::Observation>(1));
  EXPECT_GE(std::chrono::steady_clock::now() - t0, std::chrono::milliseconds(30));
  EXPECT_EQ(calls, 1);
}

TEST(FaultInjection, FailureFileBreaksAndHealsARunningPredict) {
  const auto file = tether::testing::scratch_dir() / "inject";
  std::filesystem::remove(file);
  int calls = 0;
  auto predict = with_injected_faults(counting(calls), 0, file.string());
  predict(std::vector<policy::Observation>(1));
  std::ofstream(file) << "x";
  try {
    predict(std::vector<policy::Observation>(1));
    FAIL() << "the failure file exists, yet predict ran";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::internal);
    EXPECT_NE(std::string(e.what()).find("--inject-failure-file"), std::string::npos) << e.what();
  }
  EXPECT_EQ(calls, 1) << "an injected failure must not reach the model";
  std::filesystem::remove(file);
  predict(std::vector<policy::Observation>(1));
  EXPECT_EQ(calls, 2);
}
