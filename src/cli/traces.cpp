// `tether traces verify|query|summary`: checks the hash chain of the JSON-lines traces that `tether serve --record`
// writes, filters their records into a table, JSON or CSV, and summarises success and latency per task or model.
#include <algorithm>
#include <cctype>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>

#include "cli/commands.h"
#include "core/error.h"
#include "runtime/trace_reader.h"

namespace tether::cli {

namespace {

using runtime::TraceGroupSummary;

struct TracesArgs {
  std::string dir, since, task, status = "any", model, by, output;
  std::size_t limit = 0;
  bool json = false;
};

enum class OutputFormat { json, csv };

// Checked before any trace is read, so a typo costs nothing.
std::optional<OutputFormat> output_format(const std::string& path) {
  if (path.empty()) return std::nullopt;
  auto ends_with = [&](const std::string& s) {
    return path.size() > s.size() && std::equal(s.rbegin(), s.rend(), path.rbegin(), [](char a, char b) {
             return a == std::tolower(static_cast<unsigned char>(b));
           });
  };
  if (ends_with(".json")) return OutputFormat::json;
  if (ends_with(".csv")) return OutputFormat::csv;
  throw Error(ErrorCode::invalid_argument, "--output '" + path + "': the file name must end in .json or .csv");
}

std::optional<std::chrono::milliseconds> since_of(const std::string& text) {
  if (text.empty()) return std::nullopt;
  return runtime::parse_trace_duration(text, "--since");
}

void write_file(const std::string& path, const std::string& content) {
  std::ofstream out(path, std::ios::binary);
  out << content;
  if (!out.flush()) throw Error(ErrorCode::io, path + ": cannot write");
}

// A scalar field as text: strings as they are, numbers as JSON writes them, missing or null as `none`.
std::string text_of(const Json& r, const char* key, const std::string& none = "") {
  auto it = r.find(key);
  if (it == r.end() || it->is_null()) return none;
  return it->is_string() ? it->get<std::string>() : it->dump(-1, ' ', false, Json::error_handler_t::replace);
}

// r[outer][key], or null when either is missing.
Json field_at(const Json& r, const char* outer, const char* key) {
  auto it = r.find(outer);
  if (it == r.end() || !it->is_object()) return nullptr;
  auto inner = it->find(key);
  return inner == it->end() ? Json(nullptr) : *inner;
}

std::string sub_text(const Json& r, const char* outer, const char* key, const std::string& none = "") {
  return text_of(Json{{key, field_at(r, outer, key)}}, key, none);
}

std::string csv_field(const std::string& s) {
  if (s.find_first_of(",\"\r\n") == std::string::npos) return s;
  std::string out = "\"";
  for (char c : s) out += c == '"' ? std::string("\"\"") : std::string(1, c);
  return out + "\"";
}

std::string csv(const std::vector<std::string>& header, const std::vector<std::vector<std::string>>& rows) {
  std::string out;
  auto line = [&](const std::vector<std::string>& cells) {
    for (std::size_t i = 0; i < cells.size(); ++i) out += (i ? "," : "") + csv_field(cells[i]);
    out += "\n";
  };
  line(header);
  for (const auto& r : rows) line(r);
  return out;
}

// Cuts at a UTF-8 character boundary so a long instruction never ends in half a character.
std::string clip(const std::string& s, std::size_t max) {
  if (s.size() <= max) return s;
  std::size_t n = max - 3;
  while (n > 0 && (static_cast<unsigned char>(s[n]) & 0xC0) == 0x80) --n;
  return s.substr(0, n) + "...";
}

void print_table(const std::vector<std::string>& header, const std::vector<std::vector<std::string>>& rows) {
  std::vector<std::size_t> width(header.size());
  for (std::size_t i = 0; i < header.size(); ++i) width[i] = header[i].size();
  for (const auto& r : rows)
    for (std::size_t i = 0; i < r.size(); ++i) width[i] = std::max(width[i], r[i].size());
  auto line = [&](const std::vector<std::string>& cells) {
    std::string out;
    for (std::size_t i = 0; i < cells.size(); ++i)
      out += i + 1 == cells.size() ? cells[i] : cells[i] + std::string(width[i] - cells[i].size() + 2, ' ');
    std::printf("%s\n", out.c_str());
  };
  line(header);
  for (const auto& r : rows) line(r);
}

std::string ms_text(double ms) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f", ms);
  return buf;
}

void report_corrupt(std::uint64_t corrupt) {
  if (corrupt) std::fprintf(stderr, "%llu corrupt line(s) skipped\n", static_cast<unsigned long long>(corrupt));
}

int run_verify(const TracesArgs& a) {
  const runtime::TraceVerifyReport r = runtime::verify_traces(a.dir);
  if (a.json) {
    Json problem = nullptr;
    if (r.problem)
      problem = {{"file", r.problem->file},
                 {"line", r.problem->line},
                 {"kind", runtime::trace_problem_name(r.problem->kind)},
                 {"message", r.problem->message}};
    Json out = {{"ok", r.ok()}, {"files", r.files}, {"lines", r.lines}, {"problem", problem}};
    if (r.ok()) {
      out["last_seq"] = r.last_seq;
      out["last_hash"] = r.last_hash;
    }
    std::cout << out.dump(2) << "\n";
  } else if (r.ok()) {
    std::printf("OK: %llu lines in %llu files, chain intact\n", static_cast<unsigned long long>(r.lines),
                static_cast<unsigned long long>(r.files));
  } else {
    std::printf("FAILED (%s): %s\n", runtime::trace_problem_name(r.problem->kind), r.problem->message.c_str());
  }
  return r.ok() ? kExitOk : kExitCheckFailed;
}

int run_query(const TracesArgs& a, bool limited) {
  const auto format = output_format(a.output);
  runtime::TraceFilter filter;
  filter.since = since_of(a.since);
  filter.task = a.task;
  filter.status = a.status;
  filter.model = a.model;
  if (limited) filter.limit = a.limit;
  const runtime::TraceQueryResult q = runtime::query_traces(a.dir, filter);
  report_corrupt(q.corrupt);

  if (format == OutputFormat::json || (!format && a.json)) {
    const std::string text = Json(q.records).dump(2, ' ', false, Json::error_handler_t::replace) + "\n";
    if (!format) {
      std::cout << text;
      return kExitOk;
    }
    write_file(a.output, text);
  }
  if (format == OutputFormat::csv) {
    std::vector<std::vector<std::string>> rows;
    for (const auto& r : q.records) {
      const auto actions = r.find("actions");
      rows.push_back({text_of(r, "seq"), text_of(r, "time"), text_of(r, "request_id"), text_of(r, "episode_id"),
                      text_of(r, "task"), text_of(r, "model"), text_of(r, "model_hash"), text_of(r, "status"),
                      text_of(r, "http_status"), sub_text(r, "error", "code"), sub_text(r, "error", "message"),
                      sub_text(r, "latency_ms", "total"), sub_text(r, "inputs", "seed"),
                      actions != r.end() && actions->is_array() ? std::to_string(actions->size()) : ""});
    }
    write_file(a.output, csv({"seq", "time", "request_id", "episode_id", "task", "model", "model_hash", "status",
                              "http_status", "error_code", "error_message", "latency_ms", "seed", "action_steps"},
                             rows));
  }
  if (format) {
    if (a.json) std::cout << Json{{"file", a.output}, {"records", q.records.size()}}.dump() << "\n";
    else std::printf("wrote %zu record(s) to %s\n", q.records.size(), a.output.c_str());
    return kExitOk;
  }
  if (q.records.empty()) {
    std::printf("no matching records (%llu lines read)\n", static_cast<unsigned long long>(q.lines));
    return kExitOk;
  }
  std::vector<std::vector<std::string>> rows;
  for (const auto& r : q.records) {
    const Json total = field_at(r, "latency_ms", "total");
    rows.push_back({text_of(r, "time", "-"), text_of(r, "request_id", "-"), text_of(r, "episode_id", "-"),
                    clip(text_of(r, "task", "-"), 40), text_of(r, "status", "-"),
                    total.is_number() ? ms_text(total.get<double>()) : "-", sub_text(r, "error", "code", "-")});
  }
  print_table({"time", "request_id", "episode", "task", "status", "latency_ms", "error"}, rows);
  return kExitOk;
}

Json group_json(const TraceGroupSummary& g) {
  auto ms = [&](double v) { return g.timed ? Json(v) : Json(nullptr); };
  return {{"group", g.group},
          {"count", g.count},
          {"succeeded", g.succeeded},
          {"success_rate", g.success_rate()},
          {"timed", g.timed},
          {"p50_ms", ms(g.p50_ms)},
          {"p95_ms", ms(g.p95_ms)},
          {"p99_ms", ms(g.p99_ms)},
          {"max_ms", ms(g.max_ms)}};
}

int run_summary(const TracesArgs& a) {
  const auto format = output_format(a.output);
  const runtime::TraceSummary s = runtime::summarize_traces(a.dir, a.by, since_of(a.since));
  report_corrupt(s.corrupt);
  Json groups = Json::array();
  for (const auto& g : s.groups) groups.push_back(group_json(g));
  const Json doc = {{"by", a.by}, {"records", s.records}, {"corrupt_lines", s.corrupt}, {"groups", groups}};
  const std::string doc_text = doc.dump(2, ' ', false, Json::error_handler_t::replace) + "\n";
  if (format == OutputFormat::json) write_file(a.output, doc_text);
  if (format == OutputFormat::csv) {
    const std::vector<std::string> columns = {"group",  "count",  "succeeded", "success_rate", "timed",
                                              "p50_ms", "p95_ms", "p99_ms",    "max_ms"};
    std::vector<std::vector<std::string>> rows;
    for (const auto& g : groups) {
      rows.emplace_back();
      for (const auto& c : columns) rows.back().push_back(text_of(g, c.c_str()));
    }
    write_file(a.output, csv(columns, rows));
  }
  if (format) {
    if (a.json) std::cout << Json{{"file", a.output}, {"groups", s.groups.size()}}.dump() << "\n";
    else std::printf("wrote %zu group(s) to %s\n", s.groups.size(), a.output.c_str());
    return kExitOk;
  }
  if (a.json) {
    std::cout << doc_text;
    return kExitOk;
  }
  if (s.groups.empty()) {
    std::printf("no matching records\n");
    return kExitOk;
  }
  std::vector<std::vector<std::string>> rows;
  for (const auto& g : s.groups) {
    auto ms = [&](double v) { return g.timed ? ms_text(v) : std::string("-"); };
    char rate[16];
    std::snprintf(rate, sizeof rate, "%.1f", 100.0 * g.success_rate());
    rows.push_back({clip(g.group, 48), std::to_string(g.count), rate, ms(g.p50_ms), ms(g.p95_ms), ms(g.p99_ms),
                    ms(g.max_ms)});
  }
  print_table({a.by, "count", "success_%", "p50_ms", "p95_ms", "p99_ms", "max_ms"}, rows);
  return kExitOk;
}

}  // namespace

Verb add_traces(CLI::App& app) {
  auto args = std::make_shared<TracesArgs>();
  CLI::App* sub = app.add_subcommand("traces", "Verify, query and summarise the traces of `tether serve --record DIR`");
  sub->require_subcommand(1);
  auto common = [&](CLI::App* cmd) {
    cmd->add_option("--dir", args->dir, "Trace directory (the DIR of serve --record)")->required();
    cmd->add_flag("--json", args->json, "Print JSON");
  };
  CLI::App* verify = sub->add_subcommand("verify", "Check the hash chain: no line altered, removed, reordered or torn");
  common(verify);
  CLI::App* query = sub->add_subcommand("query", "Records matching filters, as a table, JSON or CSV");
  common(query);
  query->add_option("--since", args->since, "Only records this recent: 7d, 24h, 30m, 45s");
  query->add_option("--task", args->task, "Only records whose task (instruction) contains this text");
  query->add_option("--status", args->status, "success, failed or any")
      ->check(CLI::IsMember({"success", "failed", "any"}))
      ->capture_default_str();
  query->add_option("--model", args->model, "Only records whose model name or model_hash contains this text");
  CLI::Option* limit = query->add_option("--limit", args->limit, "Only the most recent N matching records");
  query->add_option("--output", args->output, "Write FILE.json (full records) or FILE.csv (flat columns)");
  CLI::App* summary = sub->add_subcommand("summary", "Count, success rate and latency percentiles per task or model");
  common(summary);
  summary->add_option("--by", args->by, "Group by task or model")->required()->check(CLI::IsMember({"task", "model"}));
  summary->add_option("--since", args->since, "Only records this recent: 7d, 24h, 30m, 45s");
  summary->add_option("--output", args->output, "Write FILE.json or FILE.csv");
  return {sub, [args, verify, query, limit] {
            if (verify->parsed()) return run_verify(*args);
            if (query->parsed()) return run_query(*args, limit->count() > 0);
            return run_summary(*args);
          }};
}

}  // namespace tether::cli
