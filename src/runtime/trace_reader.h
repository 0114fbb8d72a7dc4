// Reading a trace directory written by TraceRecorder: verifying its hash chain, filtering records and summarising
// latency and success per task or model.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/json_util.h"

namespace tether::runtime {

enum class TraceProblemKind { altered, truncated, reordered, missing, corrupt };
const char* trace_problem_name(TraceProblemKind kind);

struct TraceProblem {
  std::string file;        // file name inside the directory, e.g. "trace-000002.jsonl"
  std::uint64_t line = 0;  // 1-based, within `file`
  TraceProblemKind kind = TraceProblemKind::corrupt;
  std::string message;     // "trace-000002.jsonl line 17: ..."
};

struct TraceVerifyReport {
  std::uint64_t files = 0, lines = 0;  // all of them, also those after the problem
  std::optional<TraceProblem> problem;  // the first one
  std::uint64_t last_seq = 0;           // the chain's tip when intact: record it elsewhere to detect a cut-off tail
  std::string last_hash;
  bool ok() const { return !problem; }
};

// Throws Error(not_found) when `dir` is missing or holds no trace files.
TraceVerifyReport verify_traces(const std::string& dir);

// "7d", "24h", "30m", "45s" or sums of them ("1h30m"); throws Error(invalid_argument) naming `flag`.
std::chrono::milliseconds parse_trace_duration(const std::string& text, const std::string& flag = "--since");

// Every member has an initializer so that designated initializers ({.status = "failed"}) compile cleanly.
struct TraceFilter {
  std::optional<std::chrono::milliseconds> since{};  // keep records whose "time" is at most this long before `now`
  std::string task{};                                // substring of "task"
  std::string status = "any";                        // success | failed | any
  std::string model{};                               // substring of "model" or "model_hash"
  std::optional<std::size_t> limit{};                // the most recent N after filtering
};

struct TraceQueryResult {
  std::vector<Json> records;  // oldest first
  std::uint64_t files = 0, lines = 0, corrupt = 0;  // corrupt: lines that are not JSON objects, skipped
};

// Never fails on corrupt lines; throws Error(not_found) when `dir` is missing or holds no trace files, and
// Error(invalid_argument) for a status other than success | failed | any.
TraceQueryResult query_traces(const std::string& dir, const TraceFilter& filter,
                              std::chrono::system_clock::time_point now = std::chrono::system_clock::now());

struct TraceGroupSummary {
  std::string group;
  std::uint64_t count = 0, succeeded = 0;
  std::uint64_t timed = 0;                        // records with a numeric latency_ms.total
  double p50_ms = 0, p95_ms = 0, p99_ms = 0, max_ms = 0;  // over `timed`; 0 when none
  double success_rate() const { return count ? double(succeeded) / double(count) : 0.0; }
};

struct TraceSummary {
  std::vector<TraceGroupSummary> groups;  // most records first, then by name
  std::uint64_t records = 0, corrupt = 0;
};

// `by`: "task" or "model". Records lacking the field are grouped under "(none)".
TraceSummary summarize_traces(const std::string& dir, const std::string& by,
                              std::optional<std::chrono::milliseconds> since,
                              std::chrono::system_clock::time_point now = std::chrono::system_clock::now());

// Nearest-rank percentile of ascending `sorted` (p in (0, 100]): the smallest value with at least p% of the values at
// or below it; always one of the data points, never interpolated. 0 for an empty vector.
double nearest_rank_percentile(const std::vector<double>& sorted, double p);

}  // namespace tether::runtime
