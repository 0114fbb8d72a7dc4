// Append-only trace of served requests: one JSON line per /act request, hash-chained across files and restarts so
// that `tether traces verify` can tell whether any line was altered, removed or reordered afterwards.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "core/json_util.h"

namespace tether::runtime {

struct TraceOptions {
  std::string dir;
  std::uint64_t max_file_bytes = 64ull << 20;  // rotate to a new file when the current one would exceed this
  enum class Fsync { every_line, interval, never } fsync = Fsync::interval;
  int fsync_interval_ms = 1000;  // for Fsync::interval
};

// "prev" of the very first line of a trace directory.
inline const std::string kTraceChainStart(64, '0');

// Trace files of `dir` ordered by their number (trace-000001.jsonl, ...); other files are ignored.
// Throws Error(not_found) when `dir` is not a directory.
std::vector<std::string> list_trace_files(const std::string& dir);
std::string trace_file_name(std::uint64_t index);  // "trace-000042.jsonl"

// UTC ISO-8601 with milliseconds: 2026-11-22T03:04:05.123Z.
std::string utc_timestamp(std::chrono::system_clock::time_point t);
// Parses what utc_timestamp writes, also with other fraction lengths or a +HH:MM / -HH:MM offset; nullopt if not.
std::optional<std::chrono::system_clock::time_point> parse_utc_timestamp(const std::string& text);

class TraceRecorder {
 public:
  // Creates `dir` and resumes the chain (seq and hash) from the newest complete line. Throws Error when the directory
  // cannot be created or read, or when its last complete line is not a trace record (the chain cannot go on).
  explicit TraceRecorder(TraceOptions options);
  ~TraceRecorder();  // fsyncs
  TraceRecorder(const TraceRecorder&) = delete;
  TraceRecorder& operator=(const TraceRecorder&) = delete;

  // Thread-safe. Puts "seq", "time" (unless the record has one) and "prev" first and writes the line with one write(2)
  // on an O_APPEND fd. I/O errors are counted and warned about once on stderr, never thrown: returns false when the
  // line was not written. Throws Error(invalid_argument) only when `record` is not a JSON object (a caller's bug).
  bool append(Json record);
  void flush();  // fsync now
  std::uint64_t lines_written() const;
  std::uint64_t write_errors() const;
  std::string current_file() const;

 private:
  struct File;
  void open_file(std::uint64_t index);  // with mu_ held; throws Error(io)
  void io_error(const std::string& what);
  void sync_loop();

  TraceOptions options_;
  mutable std::mutex mu_;
  std::shared_ptr<File> file_;  // shared so the fsync thread can sync outside mu_ while a rotation closes it
  std::uint64_t file_index_ = 0;
  bool rotate_next_ = false;  // the current file may end in a partial line: the next append starts a new file
  std::uint64_t next_seq_ = 1;
  std::string prev_hash_ = kTraceChainStart;
  bool dirty_ = false;  // written since the last fsync
  std::atomic<std::uint64_t> lines_{0}, errors_{0};
  std::atomic<bool> warned_{false};
  bool stop_ = false;
  std::condition_variable stop_cv_;
  std::thread sync_thread_;
};

}  // namespace tether::runtime
