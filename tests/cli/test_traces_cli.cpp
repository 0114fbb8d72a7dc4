// `tether traces verify|query|summary` on trace directories written by hand: exit codes, the table, JSON and CSV
// outputs, and the messages for bad input.
#include <gtest/gtest.h>

#include <chrono>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "cli_runner.h"
#include "core/hash.h"
#include "core/json_util.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

std::string now_iso() {
  const std::time_t t = std::time(nullptr);
  std::tm tm {};
  ::gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%S.000Z", &tm);
  return buf;
}

struct TraceDir {
  fs::path path;
  explicit TraceDir(const std::string& name) {
    path = tether::testing::scratch_dir() / ("traces_cli_" + name);
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~TraceDir() { fs::remove_all(path); }
  std::string arg() const { return "--dir " + path.string(); }
  fs::path file(int i) const {
    char name[32];
    std::snprintf(name, sizeof name, "trace-%06d.jsonl", i);
    return path / name;
  }

  // Chains `records` the way the recorder does (seq, time, prev first) into files of `per_file` lines.
  void write(const std::vector<Json>& records, std::size_t per_file) const {
    std::string prev(64, '0');
    for (std::size_t i = 0; i < records.size(); ++i) {
      Json line = {{"seq", i + 1}, {"time", records[i].value("time", now_iso())}, {"prev", prev}};
      for (const auto& [k, v] : records[i].items())
        if (k != "time") line[k] = v;
      const std::string text = line.dump();
      prev = sha256_hex(text);
      std::ofstream(file(int(i / per_file) + 1), std::ios::app) << text << "\n";
    }
  }
};

Json rec(const std::string& id, const std::string& task, const std::string& status, double latency,
         const std::string& model = "smolvla-demo") {
  const bool ok = status == "success";
  return {{"request_id", id},
          {"episode_id", "ep-1"},
          {"task", task},
          {"model", model},
          {"model_hash", "sha256:" + sha256_hex(model)},
          {"status", status},
          {"http_status", ok ? 200 : 504},
          {"error", ok ? Json(nullptr) : Json{{"code", "deadline_exceeded"}, {"message", "took \"too\" long"}}},
          {"inputs", {{"state", {0.5, 1.5}}, {"seed", 7}}},
          {"actions", ok ? Json::array({{0.1, 0.2}, {0.3, 0.4}, {0.5, 0.6}}) : Json(nullptr)},
          {"latency_ms", {{"total", latency}, {"predict", latency - 1}}},
          {"wedges", Json::object()}};
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

std::string slurp(const fs::path& p) {
  std::ifstream in(p);
  return {std::istreambuf_iterator<char>(in), {}};
}

}  // namespace

TEST(TracesCli, VerifyExitCodes) {
  TraceDir dir("verify");
  std::vector<Json> records;
  for (int i = 0; i < 6; ++i) records.push_back(rec("r" + std::to_string(i), "stack", "success", 10.0 + i));
  dir.write(records, 4);

  CliRun r = run_tether("traces verify " + dir.arg());
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  EXPECT_EQ(r.out, "OK: 6 lines in 2 files, chain intact\n");
  r = run_tether("traces verify --json " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  Json j = Json::parse(r.out);
  EXPECT_TRUE(j["ok"].get<bool>());
  EXPECT_EQ(j["last_seq"], 6);

  auto lines = lines_of(slurp(dir.file(1)));
  lines[1].replace(lines[1].find("\"r1\""), 4, "\"rX\"");
  std::ofstream out(dir.file(1), std::ios::trunc);
  for (const auto& l : lines) out << l << "\n";
  out.close();
  r = run_tether("traces verify " + dir.arg());
  EXPECT_EQ(r.code, 1) << r.out << r.err;
  EXPECT_EQ(r.out.rfind("FAILED (altered): trace-000001.jsonl line 3: the line before it was altered", 0), 0u) << r.out;
  r = run_tether("traces verify --json " + dir.arg());
  EXPECT_EQ(r.code, 1);
  j = Json::parse(r.out);
  EXPECT_FALSE(j["ok"].get<bool>());
  EXPECT_EQ(j["problem"]["kind"], "altered");
  EXPECT_EQ(j["problem"]["line"], 3);
  EXPECT_EQ(j["lines"], 6);

  r = run_tether("traces verify --dir " + (dir.path / "absent").string());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("no such directory"), std::string::npos) << r.err;
  TraceDir empty("verify_empty");
  r = run_tether("traces verify " + empty.arg());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("no trace files"), std::string::npos) << r.err;
  EXPECT_EQ(run_tether("traces verify").code, 2);  // --dir is required
}

TEST(TracesCli, QueryTableJsonAndCsv) {
  TraceDir dir("query");
  Json old = rec("r-old", "stack", "success", 5);
  old["time"] = "2020-01-01T00:00:00.000Z";
  dir.write({old, rec("r-1", "stack", "success", 12.5), rec("r-2", "open the drawer, then wave", "failed", 100),
             rec("r-3", "stack", "success", 14, "pi0-base"), rec("r-4", "stack", "failed", 30)},
            3);
  std::ofstream(dir.file(2), std::ios::app) << "this is not json\n";

  CliRun r = run_tether("traces query " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  auto rows = lines_of(r.out);
  ASSERT_EQ(rows.size(), 6u) << r.out;
  for (const char* col : {"time", "request_id", "episode", "task", "status", "latency_ms", "error"})
    EXPECT_NE(rows[0].find(col), std::string::npos) << col;
  EXPECT_NE(rows[1].find("2020-01-01T00:00:00.000Z"), std::string::npos) << rows[1];
  EXPECT_NE(rows[2].find("12.5"), std::string::npos) << rows[2];
  EXPECT_NE(rows[3].find("deadline_exceeded"), std::string::npos) << rows[3];
  EXPECT_EQ(r.err, "1 corrupt line(s) skipped\n");

  r = run_tether("traces query --since 7d --status success --limit 1 " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  rows = lines_of(r.out);
  ASSERT_EQ(rows.size(), 2u) << r.out;
  EXPECT_NE(rows[1].find("r-3"), std::string::npos) << r.out;

  const fs::path json_out = dir.path / "out.json";
  r = run_tether("traces query --task stack --model smolvla --output " + json_out.string() + " " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out, "wrote 3 record(s) to " + json_out.string() + "\n");
  const Json arr = Json::parse(slurp(json_out));
  ASSERT_EQ(arr.size(), 3u);
  EXPECT_EQ(arr[0]["request_id"], "r-old");
  EXPECT_EQ(arr[2]["request_id"], "r-4");
  EXPECT_EQ(arr[1]["seq"], 2);
  EXPECT_EQ(arr[1]["inputs"]["state"], Json::array({0.5, 1.5}));
  EXPECT_EQ(arr[1]["prev"].get<std::string>().size(), 64u);

  const fs::path csv_out = dir.path / "out.CSV";
  r = run_tether("traces query --status failed --output " + csv_out.string() + " " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  const auto csv = lines_of(slurp(csv_out));
  ASSERT_EQ(csv.size(), 3u);
  EXPECT_EQ(csv[0],
            "seq,time,request_id,episode_id,task,model,model_hash,status,http_status,error_code,error_message,"
            "latency_ms,seed,action_steps");
  EXPECT_NE(csv[1].find(",r-2,ep-1,\"open the drawer, then wave\",smolvla-demo,sha256:"), std::string::npos) << csv[1];
  EXPECT_NE(csv[1].find(",failed,504,deadline_exceeded,\"took \"\"too\"\" long\",100.0,7,"), std::string::npos)
      << csv[1];
  EXPECT_EQ(csv[2].substr(0, 2), "5,");

  r = run_tether("traces query --output " + (dir.path / "out.txt").string() + " " + dir.arg());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--output"), std::string::npos) << r.err;
  r = run_tether("traces query --since 3 " + dir.arg());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--since '3'"), std::string::npos) << r.err;
  EXPECT_EQ(run_tether("traces query --status ok " + dir.arg()).code, 2);
  r = run_tether("traces query --task nothing-like-this " + dir.arg());
  EXPECT_EQ(r.code, 0);
  EXPECT_EQ(r.out.rfind("no matching records", 0), 0u) << r.out;
}

TEST(TracesCli, SummaryByTaskAndModel) {
  TraceDir dir("summary");
  Json old = rec("r-old", "stack", "failed", 9000);
  old["time"] = "2020-01-01T00:00:00.000Z";
  dir.write({old, rec("a", "stack", "success", 40), rec("b", "stack", "success", 10), rec("c", "stack", "failed", 30),
             rec("d", "stack", "success", 20), rec("e", "wipe", "success", 7, "pi0-base")},
            10);

  CliRun r = run_tether("traces summary --by task --since 30d " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  const auto rows = lines_of(r.out);
  ASSERT_EQ(rows.size(), 3u) << r.out;
  auto cells = [](const std::string& row) {
    std::vector<std::string> out;
    std::istringstream in(row);
    for (std::string c; in >> c;) out.push_back(c);
    return out;
  };
  EXPECT_EQ(cells(rows[0]),
            (std::vector<std::string>{"task", "count", "success_%", "p50_ms", "p95_ms", "p99_ms", "max_ms"}));
  // Nearest rank over 10, 20, 30, 40: p50 is rank 2, p95 and p99 rank 4.
  EXPECT_EQ(cells(rows[1]), (std::vector<std::string>{"stack", "4", "75.0", "20.0", "40.0", "40.0", "40.0"}));
  EXPECT_EQ(cells(rows[2]), (std::vector<std::string>{"wipe", "1", "100.0", "7.0", "7.0", "7.0", "7.0"}));

  r = run_tether("traces summary --by model --json " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_EQ(j["records"], 6);
  ASSERT_EQ(j["groups"].size(), 2u);
  EXPECT_EQ(j["groups"][0]["group"], "smolvla-demo");
  EXPECT_EQ(j["groups"][0]["count"], 5);
  EXPECT_EQ(j["groups"][0]["max_ms"], 9000.0);
  EXPECT_DOUBLE_EQ(j["groups"][0]["success_rate"].get<double>(), 0.6);

  const fs::path csv_out = dir.path / "summary.csv";
  r = run_tether("traces summary --by task --output " + csv_out.string() + " " + dir.arg());
  ASSERT_EQ(r.code, 0) << r.err;
  const auto csv = lines_of(slurp(csv_out));
  ASSERT_EQ(csv.size(), 3u);
  EXPECT_EQ(csv[0], "group,count,succeeded,success_rate,timed,p50_ms,p95_ms,p99_ms,max_ms");
  EXPECT_EQ(csv[1], "stack,5,3,0.6,5,30.0,9000.0,9000.0,9000.0");

  EXPECT_EQ(run_tether("traces summary --by status " + dir.arg()).code, 2);
  r = run_tether("traces summary --by task --since yesterday " + dir.arg());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--since"), std::string::npos) << r.err;
}
