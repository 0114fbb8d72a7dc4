// Trace recorder and reader: the hash chain across rotation, restarts and threads; verify naming the file, line and
// kind of each tampering; query filters, corrupt lines, and nearest-rank latency percentiles.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <regex>
#include <set>
#include <thread>

#include "core/error.h"
#include "core/hash.h"
#include "runtime/trace_reader.h"
#include "runtime/trace_recorder.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::runtime;
namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

struct TempDir {
  fs::path path;
  TempDir() {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path = tether::testing::scratch_dir() / (std::string("traces_") + info->test_suite_name() + "_" + info->name());
    fs::remove_all(path);
  }
  ~TempDir() { fs::remove_all(path); }
  std::string file(int index) const { return (path / trace_file_name(std::uint64_t(index))).string(); }
};

// A record shaped like the server's.
Json server_record(int i, const std::string& task = "pick up the red cube", const std::string& status = "success",
                   double latency = 40.0, const std::string& model = "smolvla-demo") {
  const bool ok = status == "success";
  return {{"request_id", "req-" + std::to_string(i)},
          {"episode_id", i % 2 ? Json("ep-1") : Json(nullptr)},
          {"task", task},
          {"model", model},
          {"model_hash", "sha256:" + sha256_hex(model)},
          {"status", status},
          {"http_status", ok ? 200 : 503},
          {"error", ok ? Json(nullptr) : Json{{"code", "queue_full"}, {"message", "the queue is full"}}},
          {"inputs",
           {{"state", {0.1, 0.2, float(i)}},
            {"images", {{"top", {{"sha256", sha256_hex("img" + std::to_string(i))}, {"width", 64}, {"height", 48}}}}},
            {"seed", i}}},
          {"actions", ok ? Json::array({{0.5, 0.25}, {0.75, 1.0}}) : Json(nullptr)},
          {"latency_ms", {{"total", latency}, {"predict", latency * 0.8}}},
          {"wedges", Json::object()}};
}

std::vector<std::string> read_lines(const std::string& path) {
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string l; std::getline(in, l);) lines.push_back(l);
  return lines;
}

void write_lines(const std::string& path, const std::vector<std::string>& lines) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  for (const auto& l : lines) out << l << "\n";
}

void record(const std::string& dir, int n, std::uint64_t max_file_bytes = 64ull << 20) {
  TraceRecorder rec({dir, max_file_bytes, TraceOptions::Fsync::never});
  for (int i = 1; i <= n; ++i) ASSERT_TRUE(rec.append(server_record(i)));
}

void expect_problem(const std::string& dir, const std::string& file, std::uint64_t line, TraceProblemKind kind) {
  const TraceVerifyReport r = verify_traces(dir);
  ASSERT_TRUE(r.problem) << "verify found nothing wrong";
  EXPECT_EQ(r.problem->file, file) << r.problem->message;
  EXPECT_EQ(r.problem->line, line) << r.problem->message;
  EXPECT_EQ(trace_problem_name(r.problem->kind), std::string(trace_problem_name(kind))) << r.problem->message;
  EXPECT_EQ(r.problem->message.rfind(file + " line " + std::to_string(line) + ": ", 0), 0u) << r.problem->message;
}

}  // namespace

TEST(TraceRecorder, LineFormatAndChainAcrossRotationAndRestart) {
  TempDir tmp;
  const std::string dir = tmp.path.string();
  {
    TraceRecorder rec({dir, 1500, TraceOptions::Fsync::every_line});
    EXPECT_EQ(rec.current_file(), tmp.file(1));
    for (int i = 1; i <= 10; ++i) ASSERT_TRUE(rec.append(server_record(i)));
    EXPECT_EQ(rec.lines_written(), 10u);
    EXPECT_EQ(rec.write_errors(), 0u);
  }
  const auto files = list_trace_files(dir);
  ASSERT_GE(files.size(), 3u);
  std::string prev = kTraceChainStart;
  std::uint64_t seq = 0;
  for (const auto& f : files) {
    EXPECT_LE(fs::file_size(f), 1500u) << f;
    for (const auto& line : read_lines(f)) {
      const Json j = Json::parse(line);
      auto it = j.begin();
      EXPECT_EQ(it.key(), "seq");
      EXPECT_EQ((++it).key(), "time");
      EXPECT_EQ((++it).key(), "prev");
      EXPECT_EQ((++it).key(), "request_id");
      EXPECT_EQ(j["seq"].get<std::uint64_t>(), ++seq);
      EXPECT_EQ(j["prev"], prev);
      EXPECT_TRUE(std::regex_match(j["time"].get<std::string>(),
                                   std::regex(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z)")));
      EXPECT_EQ(j["task"], "pick up the red cube");
      prev = sha256_hex(line);
    }
  }
  EXPECT_EQ(seq, 10u);

  {  // a restarted server continues the chain in the newest file
    TraceRecorder rec({dir, 1500, TraceOptions::Fsync::interval, 5});
    Json r = server_record(11);
    r["time"] = "2026-11-22T03:04:05.123Z";
    r["seq"] = 999;  // the recorder's own fields win over a caller's
    ASSERT_TRUE(rec.append(r));
    ASSERT_TRUE(rec.append(server_record(12)));
  }
  const TraceVerifyReport report = verify_traces(dir);
  EXPECT_TRUE(report.ok()) << report.problem->message;
  EXPECT_EQ(report.lines, 12u);
  EXPECT_EQ(report.files, list_trace_files(dir).size());
  EXPECT_EQ(report.last_seq, 12u);
  std::vector<std::string> all;
  for (const auto& f : list_trace_files(dir))
    for (const auto& l : read_lines(f)) all.push_back(l);
  ASSERT_EQ(all.size(), 12u);
  EXPECT_EQ(report.last_hash, sha256_hex(all.back()));
  const Json eleventh = Json::parse(all[10]);
  EXPECT_EQ(eleventh["seq"], 11);
  EXPECT_EQ(eleventh["time"], "2026-11-22T03:04:05.123Z");
}

TEST(TraceRecorder, ConcurrentAppendsKeepOneChain) {
  TempDir tmp;
  constexpr int kThreads = 8, kEach = 150;
  {
    TraceRecorder rec({tmp.path.string(), 16 << 10, TraceOptions::Fsync::interval, 2});
    std::vector<std::thread> threads;
    for (int t = 0; t < kThreads; ++t)
      threads.emplace_back([&rec, t] {
        for (int i = 0; i < kEach; ++i) rec.append(server_record(t * 1000 + i));
      });
    for (auto& th : threads) th.join();
    EXPECT_EQ(rec.lines_written(), std::uint64_t(kThreads * kEach));
  }
  const TraceVerifyReport report = verify_traces(tmp.path.string());
  ASSERT_TRUE(report.ok()) << report.problem->message;
  EXPECT_EQ(report.lines, std::uint64_t(kThreads * kEach));
  EXPECT_GT(report.files, 1u);
  const TraceQueryResult all = query_traces(tmp.path.string(), {});
  std::set<std::uint64_t> seqs;
  std::set<std::string> ids;
  for (const auto& r : all.records) {
    seqs.insert(r["seq"].get<std::uint64_t>());
    ids.insert(r["request_id"].get<std::string>());
  }
  EXPECT_EQ(seqs.size(), std::size_t(kThreads * kEach));
  EXPECT_EQ(*seqs.rbegin(), std::uint64_t(kThreads * kEach));
  EXPECT_EQ(ids.size(), std::size_t(kThreads * kEach));
}

TEST(TraceRecorder, TornTailAfterCrashStartsANewFile) {
  TempDir tmp;
  const std::string dir = tmp.path.string();
  record(dir, 5);
  const std::string torn = read_lines(tmp.file(1))[2].substr(0, 100);
  std::ofstream(tmp.file(1), std::ios::app | std::ios::binary) << torn;  // a crash in the middle of write(2)
  const auto torn_size = fs::file_size(tmp.file(1));
  expect_problem(dir, "trace-000001.jsonl", 6, TraceProblemKind::truncated);

  TraceRecorder rec({dir, 64 << 20, TraceOptions::Fsync::never});
  EXPECT_EQ(rec.current_file(), tmp.file(2));
  ASSERT_TRUE(rec.append(server_record(6)));
  rec.flush();
  EXPECT_EQ(fs::file_size(tmp.file(1)), torn_size);  // left as evidence
  const auto lines = read_lines(tmp.file(2));
  ASSERT_EQ(lines.size(), 1u);
  const Json j = Json::parse(lines[0]);
  EXPECT_EQ(j["seq"], 6);
  EXPECT_EQ(j["prev"], sha256_hex(read_lines(tmp.file(1))[4]));
  // The crash stays visible: verify still names the torn line.
  expect_problem(dir, "trace-000001.jsonl", 6, TraceProblemKind::truncated);
}

TEST(TraceRecorder, WriteErrorsAreCountedNotThrown) {
  TempDir tmp;
  fs::create_directories(tmp.path);
  fs::create_symlink("/dev/full", tmp.file(1));  // every write fails with ENOSPC
  TraceRecorder rec({tmp.path.string(), 64 << 20, TraceOptions::Fsync::never});
  ::testing::internal::CaptureStderr();
  EXPECT_FALSE(rec.append(server_record(1)));
  EXPECT_FALSE(rec.append(server_record(2)));
  const std::string err = ::testing::internal::GetCapturedStderr();
  EXPECT_EQ(rec.write_errors(), 2u);
  EXPECT_EQ(rec.lines_written(), 0u);
  EXPECT_NE(err.find("No space left on device"), std::string::npos) << err;
  EXPECT_EQ(err.find("warning"), err.rfind("warning")) << "warned more than once: " << err;
  EXPECT_THROW(rec.append(Json::array({1, 2})), Error);
}

TEST(TraceRecorder, InvalidUtf8InATaskIsWrittenNotThrown) {
  TempDir tmp;
  {
    TraceRecorder rec({tmp.path.string()});
    ASSERT_TRUE(rec.append(server_record(1, std::string("pick \xff\xfe cube"))));
  }
  EXPECT_TRUE(verify_traces(tmp.path.string()).ok());
  EXPECT_EQ(query_traces(tmp.path.string(), {}).records.at(0)["task"], "pick \xEF\xBF\xBD\xEF\xBF\xBD cube");
}

TEST(TraceVerify, AlteredLine) {
  TempDir tmp;
  record(tmp.path.string(), 8);
  auto lines = read_lines(tmp.file(1));
  lines[4].replace(lines[4].find("success"), 7, "failed!");
  write_lines(tmp.file(1), lines);
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 6, TraceProblemKind::altered);
}

TEST(TraceVerify, AlteredSeqWithIntactPrev) {
  TempDir tmp;
  record(tmp.path.string(), 8);
  auto lines = read_lines(tmp.file(1));
  lines[4].replace(0, std::string("{\"seq\":5").size(), "{\"seq\":50");
  write_lines(tmp.file(1), lines);
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 5, TraceProblemKind::altered);
}

TEST(TraceVerify, DeletedLine) {
  TempDir tmp;
  record(tmp.path.string(), 8);
  auto lines = read_lines(tmp.file(1));
  lines.erase(lines.begin() + 4);
  write_lines(tmp.file(1), lines);
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 5, TraceProblemKind::missing);
  EXPECT_NE(verify_traces(tmp.path.string()).problem->message.find("seq jumps from 4 to 6"), std::string::npos);
}

TEST(TraceVerify, SwappedLines) {
  TempDir tmp;
  record(tmp.path.string(), 8);
  auto lines = read_lines(tmp.file(1));
  std::swap(lines[3], lines[4]);
  write_lines(tmp.file(1), lines);
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 4, TraceProblemKind::reordered);
}

TEST(TraceVerify, SwappedFilesAreReordered) {
  TempDir tmp;
  record(tmp.path.string(), 9, 1500);
  ASSERT_GE(list_trace_files(tmp.path.string()).size(), 3u);
  fs::rename(tmp.file(2), tmp.path / "x");
  fs::rename(tmp.file(3), tmp.file(2));
  fs::rename(tmp.path / "x", tmp.file(3));
  expect_problem(tmp.path.string(), "trace-000002.jsonl", 1, TraceProblemKind::reordered);
}

TEST(TraceVerify, TruncatedTail) {
  TempDir tmp;
  record(tmp.path.string(), 4);
  const std::string half = read_lines(tmp.file(1))[3].substr(0, 120);
  std::ofstream(tmp.file(1), std::ios::app | std::ios::binary) << half;
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 5, TraceProblemKind::truncated);
  EXPECT_EQ(verify_traces(tmp.path.string()).lines, 5u);
}

TEST(TraceVerify, DeletedFirstAndMiddleFiles) {
  TempDir tmp;
  record(tmp.path.string(), 12, 1500);
  ASSERT_GE(list_trace_files(tmp.path.string()).size(), 4u);
  fs::remove(tmp.file(3));
  expect_problem(tmp.path.string(), "trace-000004.jsonl", 1, TraceProblemKind::missing);
  fs::remove(tmp.file(1));
  expect_problem(tmp.path.string(), "trace-000002.jsonl", 1, TraceProblemKind::missing);
}

TEST(TraceVerify, CorruptLineAndEmptyDirectory) {
  TempDir tmp;
  record(tmp.path.string(), 5);
  auto lines = read_lines(tmp.file(1));
  lines[2] = "{\"seq\": 3, oops";
  write_lines(tmp.file(1), lines);
  expect_problem(tmp.path.string(), "trace-000001.jsonl", 3, TraceProblemKind::corrupt);

  TempDir empty;
  fs::create_directories(empty.path / "sub");
  std::ofstream(empty.path / "notes.txt") << "hello\n";
  EXPECT_THROW(verify_traces(empty.path.string()), Error);
  EXPECT_THROW(verify_traces((empty.path / "absent").string()), Error);
  // A restart with a corrupt last line refuses to extend a chain it cannot link to.
  TempDir bad;
  fs::create_directories(bad.path);
  write_lines((bad.path / trace_file_name(1)).string(), {"not json"});
  EXPECT_THROW(TraceRecorder({bad.path.string()}), Error);
}

TEST(TraceQuery, CorruptLinesAreSkippedAndCounted) {
  TempDir tmp;
  record(tmp.path.string(), 6);
  auto lines = read_lines(tmp.file(1));
  lines.insert(lines.begin() + 2, "garbage");
  lines.insert(lines.begin() + 4, "[1, 2, 3]");
  write_lines(tmp.file(1), lines);
  std::ofstream(tmp.file(1), std::ios::app) << "{\"seq\": 7, \"tor";
  const TraceQueryResult q = query_traces(tmp.path.string(), {});
  EXPECT_EQ(q.records.size(), 6u);
  EXPECT_EQ(q.corrupt, 3u);
  EXPECT_EQ(q.lines, 9u);
  EXPECT_EQ(summarize_traces(tmp.path.string(), "task", std::nullopt).corrupt, 3u);
}

TEST(TraceQuery, Filters) {
  TempDir tmp;
  const auto now = std::chrono::system_clock::now();
  {
    TraceRecorder rec({tmp.path.string()});
    auto add = [&](int i, std::chrono::hours age, const std::string& task, const std::string& status,
                   const std::string& model) {
      Json r = server_record(i, task, status, 10.0 * i, model);
      r["time"] = utc_timestamp(now - age);
      ASSERT_TRUE(rec.append(r));
    };
    add(1, 24h * 10, "pick up the red cube", "success", "smolvla-demo");
    add(2, 24h * 3, "pick up the red cube", "failed", "smolvla-demo");
    add(3, 30h, "open the drawer", "success", "pi0-base");
    add(4, 2h, "open the drawer", "failed", "pi0-base");
    add(5, 1h, "pick up the red cube", "success", "smolvla-demo");
    add(6, 0h, "pick up the blue cube", "success", "smolvla-demo");
  }
  Json untimed = server_record(7);  // a record without a readable time is never "recent"
  untimed["time"] = "yesterday";
  {
    TraceRecorder rec({tmp.path.string()});
    rec.append(untimed);
  }
  auto ids = [&](const TraceFilter& f) {
    std::vector<std::string> out;
    for (const auto& r : query_traces(tmp.path.string(), f, now).records)
      out.push_back(r["request_id"].get<std::string>());
    return out;
  };
  using V = std::vector<std::string>;
  EXPECT_EQ(ids({}), (V{"req-1", "req-2", "req-3", "req-4", "req-5", "req-6", "req-7"}));
  EXPECT_EQ(ids({.since = parse_trace_duration("7d")}), (V{"req-2", "req-3", "req-4", "req-5", "req-6"}));
  EXPECT_EQ(ids({.since = parse_trace_duration("24h")}), (V{"req-4", "req-5", "req-6"}));
  EXPECT_EQ(ids({.since = parse_trace_duration("90m")}), (V{"req-5", "req-6"}));
  EXPECT_EQ(ids({.task = "red cube"}), (V{"req-1", "req-2", "req-5", "req-7"}));
  EXPECT_EQ(ids({.status = "failed"}), (V{"req-2", "req-4"}));
  EXPECT_EQ(ids({.status = "success", .model = "pi0"}), (V{"req-3"}));
  EXPECT_EQ(ids({.model = sha256_hex("pi0-base").substr(0, 12)}), (V{"req-3", "req-4"}));
  EXPECT_EQ(ids({.task = "cube", .limit = 2}), (V{"req-6", "req-7"}));
  EXPECT_EQ(ids({.status = "success", .model = "smolvla", .limit = 3}), (V{"req-5", "req-6", "req-7"}));
  EXPECT_EQ(ids({.limit = 0}), V{});
  EXPECT_THROW(query_traces(tmp.path.string(), {.status = "ok"}), Error);
}

TEST(TraceQuery, Durations) {
  EXPECT_EQ(parse_trace_duration("7d"), std::chrono::hours(168));
  EXPECT_EQ(parse_trace_duration("24h"), std::chrono::hours(24));
  EXPECT_EQ(parse_trace_duration("30m"), std::chrono::minutes(30));
  EXPECT_EQ(parse_trace_duration("45s"), std::chrono::seconds(45));
  EXPECT_EQ(parse_trace_duration("1h30m"), std::chrono::minutes(90));
  for (const char* bad : {"", "7", "d", "7x", "-1h", "1.5h", "7 d", "99999999999s"}) {
    try {
      parse_trace_duration(bad);
      ADD_FAILURE() << "accepted '" << bad << "'";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("--since"), std::string::npos) << e.what();
    }
  }
}

TEST(TraceQuery, Timestamps) {
  const auto t = std::chrono::system_clock::from_time_t(1795316645) + 123ms;
  EXPECT_EQ(utc_timestamp(t), "2026-11-22T03:04:05.123Z");
  EXPECT_EQ(parse_utc_timestamp("2026-11-22T03:04:05.123Z"), t);
  EXPECT_EQ(parse_utc_timestamp("2026-11-22T04:04:05.123+01:00"), t);
  EXPECT_EQ(parse_utc_timestamp("2026-11-22T03:04:05.1234567Z"), t);
  EXPECT_EQ(parse_utc_timestamp("2026-11-22T03:04:05Z"), t - 123ms);
  for (const char* bad : {"", "2026-11-22", "2026-11-22T03:04:05", "2026-13-22T03:04:05Z", "2026-11-22T03:04:05.Z"})
    EXPECT_FALSE(parse_utc_timestamp(bad)) << bad;
}

TEST(TraceSummary, NearestRankPercentilesPerGroup) {
  TempDir tmp;
  const auto now = std::chrono::system_clock::now();
  {
    TraceRecorder rec({tmp.path.string()});
    // "stack": latencies 1..100 ms, every 4th failed; "wipe": 20 values 5, 10, ..., 100 in shuffled order.
    for (int i = 1; i <= 100; ++i)
      rec.append(server_record(i, "stack", i % 4 == 0 ? "failed" : "success", double(i), "m-a"));
    for (int k : {7, 3, 19, 1, 20, 12, 5, 16, 9, 14, 2, 11, 18, 6, 15, 4, 13, 8, 17, 10})
      rec.append(server_record(100 + k, "wipe", "success", 5.0 * k, "m-b"));
    Json old = server_record(200, "wipe", "failed", 1e6, "m-b");
    old["time"] = utc_timestamp(now - 48h);
    rec.append(old);
    Json untimed = server_record(201, "stack", "success", 40.0, "m-a");
    untimed.erase("latency_ms");
    untimed.erase("task");
    rec.append(untimed);
  }
  const TraceSummary s = summarize_traces(tmp.path.string(), "task", parse_trace_duration("24h"), now);
  EXPECT_EQ(s.records, 121u);
  ASSERT_EQ(s.groups.size(), 3u);
  const TraceGroupSummary& stack = s.groups[0];
  EXPECT_EQ(stack.group, "stack");
  EXPECT_EQ(stack.count, 100u);
  EXPECT_DOUBLE_EQ(stack.success_rate(), 0.75);
  EXPECT_EQ(stack.p50_ms, 50);
  EXPECT_EQ(stack.p95_ms, 95);
  EXPECT_EQ(stack.p99_ms, 99);
  EXPECT_EQ(stack.max_ms, 100);
  const TraceGroupSummary& wipe = s.groups[1];
  EXPECT_EQ(wipe.group, "wipe");
  EXPECT_EQ(wipe.count, 20u);
  EXPECT_EQ(wipe.p50_ms, 50);  // rank ceil(0.5 * 20) = 10
  EXPECT_EQ(wipe.p95_ms, 95);  // rank 19
  EXPECT_EQ(wipe.p99_ms, 100);  // rank ceil(19.8) = 20
  EXPECT_EQ(wipe.max_ms, 100);
  EXPECT_EQ(s.groups[2].group, "(none)");
  EXPECT_EQ(s.groups[2].timed, 0u);

  const TraceSummary all = summarize_traces(tmp.path.string(), "model", std::nullopt, now);
  ASSERT_EQ(all.groups.size(), 2u);
  EXPECT_EQ(all.groups[1].group, "m-b");
  EXPECT_EQ(all.groups[1].count, 21u);
  EXPECT_EQ(all.groups[1].max_ms, 1e6);
  EXPECT_THROW(summarize_traces(tmp.path.string(), "status", std::nullopt), Error);

  EXPECT_EQ(nearest_rank_percentile({10, 20, 30}, 50), 20);
  EXPECT_EQ(nearest_rank_percentile({10, 20, 30}, 99), 30);
  EXPECT_EQ(nearest_rank_percentile({10}, 1), 10);
  EXPECT_EQ(nearest_rank_percentile({}, 50), 0);
}
