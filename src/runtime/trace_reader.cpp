// Trace directory reader: streams lines across files in order; verification stops checking at the first problem,
// queries and summaries skip (and count) lines that are not JSON objects.
#include "runtime/trace_reader.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>

#include "core/error.h"
#include "core/hash.h"
#include "runtime/trace_recorder.h"

namespace tether::runtime {

namespace fs = std::filesystem;
using SysClock = std::chrono::system_clock;

namespace {

std::vector<std::string> trace_files_or_throw(const std::string& dir) {
  auto files = list_trace_files(dir);
  if (files.empty())
    throw Error(ErrorCode::not_found, dir + ": no trace files (trace-NNNNNN.jsonl) in this directory; is it the one "
                                            "given to `tether serve --record`?");
  return files;
}

struct TraceLine {
  std::string file;  // name inside the directory
  std::uint64_t number = 0;
  std::string text;
  bool torn = false;  // no newline at its end
};

// Lines of all files in order.
class LineReader {
 public:
  explicit LineReader(std::vector<std::string> files) : files_(std::move(files)) {}

  std::optional<TraceLine> next() {
    for (;;) {
      if (!in_.is_open()) {
        if (index_ == files_.size()) return std::nullopt;
        in_.open(files_[index_], std::ios::binary);
        if (!in_) throw Error(ErrorCode::io, files_[index_] + ": cannot open");
        number_ = 0;
      }
      TraceLine line;
      if (std::getline(in_, line.text)) {
        line.file = fs::path(files_[index_]).filename().string();
        line.number = ++number_;
        line.torn = in_.eof();  // getline reached the end of the file before a newline
        return line;
      }
      if (!in_.eof()) throw Error(ErrorCode::io, files_[index_] + ": read error");
      in_.close();
      ++index_;
    }
  }

 private:
  std::vector<std::string> files_;
  std::size_t index_ = 0;
  std::ifstream in_;
  std::uint64_t number_ = 0;
};

Json parse_object(const std::string& text) {
  Json j = Json::parse(text, nullptr, /*allow_exceptions=*/false);
  return j.is_object() ? j : Json();
}

std::optional<std::uint64_t> seq_of(const Json& record) {
  auto it = record.find("seq");
  if (it == record.end() || !it->is_number_unsigned()) return std::nullopt;
  return it->get<std::uint64_t>();
}

std::optional<std::string> string_field(const Json& record, const char* key) {
  auto it = record.find(key);
  if (it == record.end() || !it->is_string()) return std::nullopt;
  return it->get<std::string>();
}

std::string checked_status(const std::string& status) {
  if (status != "success" && status != "failed" && status != "any")
    throw Error(ErrorCode::invalid_argument,
                "trace filter: status must be success, failed or any, not '" + status + "'");
  return status;
}

bool matches(const Json& r, const TraceFilter& f, std::optional<SysClock::time_point> cutoff) {
  if (cutoff) {
    // A record without a readable time cannot be shown to be recent, so --since leaves it out.
    const auto time = string_field(r, "time");
    const auto t = time ? parse_utc_timestamp(*time) : std::nullopt;
    if (!t || *t < *cutoff) return false;
  }
  if (!f.task.empty()) {
    const auto task = string_field(r, "task");
    if (!task || task->find(f.task) == std::string::npos) return false;
  }
  if (f.status != "any" && string_field(r, "status") != f.status) return false;
  if (!f.model.empty()) {
    const auto model = string_field(r, "model"), hash = string_field(r, "model_hash");
    if (!(model && model->find(f.model) != std::string::npos) && !(hash && hash->find(f.model) != std::string::npos))
      return false;
  }
  return true;
}

struct ReadStats {
  std::uint64_t files = 0, lines = 0, corrupt = 0;
};

template <typename Fn>
ReadStats for_each_record(const std::string& dir, Fn&& fn) {
  const auto files = trace_files_or_throw(dir);
  ReadStats stats;
  stats.files = files.size();
  LineReader reader(files);
  while (auto line = reader.next()) {
    ++stats.lines;
    Json record = parse_object(line->text);
    if (record.is_null()) ++stats.corrupt;
    else fn(std::move(record));
  }
  return stats;
}

std::optional<SysClock::time_point> cutoff_of(std::optional<std::chrono::milliseconds> since,
                                              SysClock::time_point now) {
  if (!since) return std::nullopt;
  return now - *since;
}

}  // namespace

const char* trace_problem_name(TraceProblemKind kind) {
  switch (kind) {
    case TraceProblemKind::altered: return "altered";
    case TraceProblemKind::truncated: return "truncated";
    case TraceProblemKind::reordered: return "reordered";
    case TraceProblemKind::missing: return "missing";
    case TraceProblemKind::corrupt: return "corrupt";
  }
  return "?";
}

TraceVerifyReport verify_traces(const std::string& dir) {
  const auto files = trace_files_or_throw(dir);
  TraceVerifyReport report;
  report.files = files.size();
  LineReader reader(files);
  bool started = false;
  std::uint64_t prev_seq = 0;
  std::string prev_hash = kTraceChainStart;

  // Returns the problem with `line`, or nullopt and advances the chain.
  auto check = [&](const TraceLine& line) -> std::optional<std::pair<TraceProblemKind, std::string>> {
    using K = TraceProblemKind;
    if (line.torn)
      return {{K::truncated, "the line is cut short (no newline at its end): the writer stopped mid-line, after a "
                             "crash or with a full disk"}};
    const Json record = parse_object(line.text);
    if (record.is_null()) return {{K::corrupt, "not a JSON object"}};
    const auto seq = seq_of(record);
    const auto prev = string_field(record, "prev");
    if (!seq) return {{K::corrupt, "no \"seq\" (an unsigned integer)"}};
    if (!prev || !is_sha256_hex(*prev)) return {{K::corrupt, "no \"prev\" (64 hex digits)"}};
    const std::string s = std::to_string(*seq);
    if (!started) {
      if (*prev != kTraceChainStart)
        return {{K::missing, "the lines before it are missing: it is seq " + s +
                                 " and its prev is not the start of a chain (an earlier file, or the start of this "
                                 "one, was removed)"}};
    } else if (*seq == prev_seq + 1) {
      if (*prev != prev_hash)
        return {{K::altered, "the line before it was altered (its hash does not match this line's prev)"}};
    } else if (*prev == prev_hash) {
      return {{K::altered, "its seq was altered (" + s + " where " + std::to_string(prev_seq + 1) +
                               " belongs, though its prev matches the line before)"}};
    } else if (*seq <= prev_seq) {
      return {{K::reordered, "lines are out of order: seq " + s + " comes after seq " + std::to_string(prev_seq)}};
    } else {
      // A jump forward: the skipped seq further on means lines (or files) were moved, else they are gone. This
      // second pass over the directory happens once, on the first problem.
      const std::string skipped = std::to_string(prev_seq + 1);
      LineReader rest(files);
      while (auto later = rest.next())
        if (seq_of(parse_object(later->text)) == prev_seq + 1)
          return {{K::reordered, "lines are out of order: seq " + s + " comes before seq " + skipped + " (" +
                                     later->file + " line " + std::to_string(later->number) + ")"}};
      const std::uint64_t gone = *seq - prev_seq - 1;
      return {{K::missing, std::to_string(gone) + (gone == 1 ? " line is" : " lines are") +
                               " missing before it (seq jumps from " + std::to_string(prev_seq) + " to " + s + ")"}};
    }
    started = true;
    prev_seq = *seq;
    prev_hash = sha256_hex(line.text);
    return std::nullopt;
  };

  while (auto line = reader.next()) {
    ++report.lines;
    if (!report.problem)
      if (auto p = check(*line))
        report.problem = TraceProblem{line->file, line->number, p->first,
                                      line->file + " line " + std::to_string(line->number) + ": " + p->second};
  }
  if (!report.problem) {
    report.last_seq = prev_seq;
    report.last_hash = started ? prev_hash : "";
  }
  return report;
}

std::chrono::milliseconds parse_trace_duration(const std::string& text, const std::string& flag) {
  const Error bad(ErrorCode::invalid_argument,
                  flag + " '" + text + "': not a duration; use a number and a unit d, h, m or s (7d, 24h, 30m, 45s)");
  std::chrono::milliseconds total{0};
  std::size_t i = 0;
  if (text.empty()) throw bad;
  while (i < text.size()) {
    std::int64_t n = 0;
    std::size_t digits = 0;
    for (; i < text.size() && text[i] >= '0' && text[i] <= '9'; ++i, ++digits) n = n * 10 + (text[i] - '0');
    if (digits == 0 || digits > 9 || i == text.size()) throw bad;
    switch (text[i++]) {
      case 'd': total += std::chrono::hours(24 * n); break;
      case 'h': total += std::chrono::hours(n); break;
      case 'm': total += std::chrono::minutes(n); break;
      case 's': total += std::chrono::seconds(n); break;
      default: throw bad;
    }
  }
  return total;
}

TraceQueryResult query_traces(const std::string& dir, const TraceFilter& filter, SysClock::time_point now) {
  checked_status(filter.status);
  const auto cutoff = cutoff_of(filter.since, now);
  std::deque<Json> kept;
  const ReadStats stats = for_each_record(dir, [&](Json record) {
    if (!matches(record, filter, cutoff)) return;
    kept.push_back(std::move(record));
    if (filter.limit && kept.size() > *filter.limit) kept.pop_front();
  });
  TraceQueryResult result;
  result.records.assign(std::make_move_iterator(kept.begin()), std::make_move_iterator(kept.end()));
  result.files = stats.files;
  result.lines = stats.lines;
  result.corrupt = stats.corrupt;
  return result;
}

double nearest_rank_percentile(const std::vector<double>& sorted, double p) {
  if (sorted.empty()) return 0;
  // rank = ceil(p/100 * n), computed as p*n/100 so that e.g. p95 of 20 values is exactly rank 19.
  const double rank = std::ceil(p * double(sorted.size()) / 100.0);
  const std::size_t r = std::clamp<std::size_t>(std::size_t(std::max(rank, 1.0)), 1, sorted.size());
  return sorted[r - 1];
}

TraceSummary summarize_traces(const std::string& dir, const std::string& by,
                              std::optional<std::chrono::milliseconds> since, SysClock::time_point now) {
  if (by != "task" && by != "model")
    throw Error(ErrorCode::invalid_argument, "trace summary: group by task or model, not '" + by + "'");
  TraceFilter filter;
  filter.since = since;
  const auto cutoff = cutoff_of(since, now);
  struct Group {
    TraceGroupSummary summary;
    std::vector<double> latencies;
  };
  std::map<std::string, Group> groups;
  TraceSummary out;
  const ReadStats stats = for_each_record(dir, [&](Json r) {
    if (!matches(r, filter, cutoff)) return;
    std::optional<std::string> key = string_field(r, by.c_str());
    if (!key && by == "model") key = string_field(r, "model_hash");
    Group& g = groups[key.value_or("(none)")];
    ++g.summary.count;
    ++out.records;
    if (string_field(r, "status") == "success") ++g.summary.succeeded;
    // Failed requests count too: a deadline that expired is latency a client waited through.
    const auto lat = r.find("latency_ms");
    if (lat != r.end() && lat->is_object())
      if (auto total = lat->find("total"); total != lat->end() && total->is_number())
        g.latencies.push_back(total->get<double>());
  });
  out.corrupt = stats.corrupt;
  for (auto& [name, g] : groups) {
    std::sort(g.latencies.begin(), g.latencies.end());
    g.summary.group = name;
    g.summary.timed = g.latencies.size();
    g.summary.p50_ms = nearest_rank_percentile(g.latencies, 50);
    g.summary.p95_ms = nearest_rank_percentile(g.latencies, 95);
    g.summary.p99_ms = nearest_rank_percentile(g.latencies, 99);
    g.summary.max_ms = g.latencies.empty() ? 0 : g.latencies.back();
    out.groups.push_back(std::move(g.summary));
  }
  std::stable_sort(out.groups.begin(), out.groups.end(),
                   [](const TraceGroupSummary& a, const TraceGroupSummary& b) { return a.count > b.count; });
  return out;
}

}  // namespace tether::runtime
