// Trace recorder: whole lines through one write(2) on an O_APPEND fd, a sha256 chain resumed from disk on start, and
// fsync either per line, from a background thread every interval, or only on flush and shutdown.
#include "runtime/trace_recorder.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>

#include "core/error.h"
#include "core/hash.h"

namespace tether::runtime {

namespace fs = std::filesystem;
using SysClock = std::chrono::system_clock;

namespace {

constexpr const char* kPrefix = "trace-";
constexpr const char* kSuffix = ".jsonl";

std::optional<std::uint64_t> trace_file_index(const std::string& name) {
  const std::size_t p = std::strlen(kPrefix), s = std::strlen(kSuffix);
  if (name.size() <= p + s || name.size() > p + s + 19 || name.compare(0, p, kPrefix) != 0 ||
      name.compare(name.size() - s, s, kSuffix) != 0)
    return std::nullopt;
  const std::string digits = name.substr(p, name.size() - p - s);
  if (!std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) return std::nullopt;
  return std::stoull(digits);
}

struct Fd {
  int fd;
  explicit Fd(int f) : fd(f) {}
  ~Fd() {
    if (fd >= 0) ::close(fd);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
};

// The last line of a file that ends in a newline (without it), and whether bytes follow it (a torn line).
struct Tail {
  std::optional<std::string> line;
  bool torn = false;
};

Tail read_tail(const std::string& path) {
  Fd f(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
  struct stat st {};
  if (f.fd < 0 || ::fstat(f.fd, &st) != 0)
    throw Error(ErrorCode::io, path + ": cannot read (" + std::strerror(errno) + ")");
  Tail tail;
  // Read backwards in doubling blocks (a line with full images can be megabytes) until the last complete line is
  // bounded by the newline before it or by the start of the file.
  std::string buf;
  off_t pos = st.st_size;
  std::size_t block = 1 << 16;
  while (pos > 0) {
    const off_t n = std::min<off_t>(pos, off_t(block));
    std::string chunk(std::size_t(n), '\0');
    for (off_t done = 0; done < n;) {
      const ssize_t r = ::pread(f.fd, chunk.data() + done, std::size_t(n - done), pos - n + done);
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) throw Error(ErrorCode::io, path + ": cannot read (" + std::strerror(r < 0 ? errno : EIO) + ")");
      done += r;
    }
    if (buf.empty()) tail.torn = chunk.back() != '\n';
    buf.insert(0, chunk);
    pos -= n;
    block *= 2;
    const std::size_t end = buf.rfind('\n');
    if (end == std::string::npos) continue;
    const std::size_t before = end == 0 ? std::string::npos : buf.rfind('\n', end - 1);
    if (before != std::string::npos) {
      tail.line = buf.substr(before + 1, end - before - 1);
      break;
    }
    if (pos == 0) tail.line = buf.substr(0, end);
  }
  return tail;
}

void sync_dir(const std::string& dir) {
  Fd d(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (d.fd >= 0) ::fsync(d.fd);  // best effort: makes a new file's directory entry durable
}

}  // namespace

std::string trace_file_name(std::uint64_t index) {
  char buf[48];
  std::snprintf(buf, sizeof buf, "%s%06llu%s", kPrefix, static_cast<unsigned long long>(index), kSuffix);
  return buf;
}

std::vector<std::string> list_trace_files(const std::string& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) throw Error(ErrorCode::not_found, dir + ": no such directory");
  std::vector<std::pair<std::uint64_t, std::string>> found;
  for (const auto& entry : fs::directory_iterator(dir, ec))
    if (auto index = trace_file_index(entry.path().filename().string()); index && entry.is_regular_file())
      found.emplace_back(*index, entry.path().string());
  if (ec) throw Error(ErrorCode::io, dir + ": cannot list (" + ec.message() + ")");
  // By number, not by name: past trace-999999 the names grow a digit and lexical order breaks.
  std::sort(found.begin(), found.end());
  std::vector<std::string> paths;
  for (auto& f : found) paths.push_back(std::move(f.second));
  return paths;
}

std::string utc_timestamp(SysClock::time_point t) {
  const auto secs = std::chrono::floor<std::chrono::seconds>(t);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(t - secs).count();
  const std::time_t tt = SysClock::to_time_t(secs);
  std::tm tm {};
  ::gmtime_r(&tt, &tm);
  char buf[96];
  std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tm.tm_year + 1900, tm.tm_mon + 1, tm.tm_mday,
                tm.tm_hour, tm.tm_min, tm.tm_sec, int(ms));
  return buf;
}

std::optional<SysClock::time_point> parse_utc_timestamp(const std::string& s) {
  auto num = [&](std::size_t pos, std::size_t len) -> int {
    if (pos + len > s.size()) return -1;
    int v = 0;
    for (std::size_t i = pos; i < pos + len; ++i) {
      if (s[i] < '0' || s[i] > '9') return -1;
      v = v * 10 + (s[i] - '0');
    }
    return v;
  };
  if (s.size() < 20 || s[4] != '-' || s[7] != '-' || (s[10] != 'T' && s[10] != ' ') || s[13] != ':' || s[16] != ':')
    return std::nullopt;
  std::tm tm {};
  tm.tm_year = num(0, 4) - 1900;
  tm.tm_mon = num(5, 2) - 1;
  tm.tm_mday = num(8, 2);
  tm.tm_hour = num(11, 2);
  tm.tm_min = num(14, 2);
  tm.tm_sec = num(17, 2);
  if (tm.tm_year < -1900 || tm.tm_mon < 0 || tm.tm_mon > 11 || tm.tm_mday < 1 || tm.tm_mday > 31 || tm.tm_hour < 0 ||
      tm.tm_hour > 23 || tm.tm_min < 0 || tm.tm_min > 59 || tm.tm_sec < 0 || tm.tm_sec > 60)
    return std::nullopt;
  std::size_t pos = 19;
  int ms = 0;
  if (s[pos] == '.') {
    std::size_t digits = 0;
    for (++pos; pos < s.size() && s[pos] >= '0' && s[pos] <= '9'; ++pos, ++digits)
      if (digits < 3) ms = ms * 10 + (s[pos] - '0');
    if (digits == 0) return std::nullopt;
    for (; digits < 3; ++digits) ms *= 10;
  }
  long offset_s = 0;
  if (pos + 1 == s.size() && (s[pos] == 'Z' || s[pos] == 'z')) {
  } else if (pos + 6 == s.size() && (s[pos] == '+' || s[pos] == '-') && s[pos + 3] == ':') {
    const int h = num(pos + 1, 2), m = num(pos + 4, 2);
    if (h < 0 || m < 0) return std::nullopt;
    offset_s = (s[pos] == '+' ? 1 : -1) * (h * 3600L + m * 60L);
  } else {
    return std::nullopt;
  }
  const std::time_t t = ::timegm(&tm) - offset_s;
  return SysClock::from_time_t(t) + std::chrono::milliseconds(ms);
}

struct TraceRecorder::File {
  Fd fd;
  std::string path;
  std::uint64_t size = 0;
  File(int f, std::string p) : fd(f), path(std::move(p)) {}
};

TraceRecorder::TraceRecorder(TraceOptions options) : options_(std::move(options)) {
  if (options_.dir.empty()) throw Error(ErrorCode::invalid_argument, "trace recorder: no directory given");
  if (options_.max_file_bytes == 0)
    throw Error(ErrorCode::invalid_argument, "trace recorder: max_file_bytes must be positive");
  if (options_.fsync == TraceOptions::Fsync::interval && options_.fsync_interval_ms <= 0)
    throw Error(ErrorCode::invalid_argument, "trace recorder: fsync_interval_ms must be positive");
  std::error_code ec;
  fs::create_directories(options_.dir, ec);
  if (ec) throw Error(ErrorCode::io, options_.dir + ": cannot create the trace directory (" + ec.message() + ")");
  const auto files = list_trace_files(options_.dir);
  // The chain resumes from the newest complete line, looking back past files that hold none (empty, or one torn
  // line). A torn newest file is left as it is, evidence of the crash, and the next line goes to a new file.
  bool torn = false;
  for (auto it = files.rbegin(); it != files.rend(); ++it) {
    const Tail tail = read_tail(*it);
    if (it == files.rbegin()) torn = tail.torn;
    if (!tail.line) continue;
    const Json last = Json::parse(*tail.line, nullptr, /*allow_exceptions=*/false);
    const auto seq = last.is_object() ? last.find("seq") : last.end();
    if (!last.is_object() || seq == last.end() || !seq->is_number_unsigned())
      throw Error(ErrorCode::format, *it + ": the last complete line is not a trace record, so the hash chain cannot "
                                         "go on; check the directory with `tether traces verify --dir " +
                                         options_.dir + "` or record into another one");
    next_seq_ = seq->get<std::uint64_t>() + 1;
    prev_hash_ = sha256_hex(*tail.line);
    break;
  }
  const std::uint64_t newest = files.empty() ? 0 : *trace_file_index(fs::path(files.back()).filename().string());
  open_file(files.empty() ? 1 : newest + (torn ? 1 : 0));
  if (options_.fsync == TraceOptions::Fsync::interval) sync_thread_ = std::thread([this] { sync_loop(); });
}

TraceRecorder::~TraceRecorder() {
  {
    std::lock_guard lock(mu_);
    stop_ = true;
  }
  stop_cv_.notify_all();
  if (sync_thread_.joinable()) sync_thread_.join();
  flush();
}

void TraceRecorder::open_file(std::uint64_t index) {
  const std::string path = (fs::path(options_.dir) / trace_file_name(index)).string();
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  struct stat st {};
  if (fd < 0 || ::fstat(fd, &st) != 0) {
    const int err = errno;
    if (fd >= 0) ::close(fd);
    throw Error(ErrorCode::io, path + ": cannot open for appending (" + std::strerror(err) + ")");
  }
  auto file = std::make_shared<File>(fd, path);
  file->size = std::uint64_t(st.st_size);
  if (options_.fsync != TraceOptions::Fsync::never) {
    if (file_ && dirty_ && ::fdatasync(file_->fd.fd) != 0)
      io_error(file_->path + ": cannot fsync (" + std::strerror(errno) + ")");
    dirty_ = false;
    sync_dir(options_.dir);
  }
  file_ = std::move(file);
  file_index_ = index;
  rotate_next_ = false;
}

void TraceRecorder::io_error(const std::string& what) {
  ++errors_;
  if (!warned_.exchange(true))
    std::fprintf(stderr,
                 "warning: trace recorder: %s; serving goes on, further trace errors are counted, not printed\n",
                 what.c_str());
}

bool TraceRecorder::append(Json record) {
  if (!record.is_object())
    throw Error(ErrorCode::invalid_argument,
                std::string("trace record must be a JSON object, got ") + record.type_name());
  std::optional<std::string> time;
  if (auto t = record.find("time"); t != record.end() && t->is_string()) time = t->get<std::string>();
  for (const char* k : {"seq", "time", "prev"}) record.erase(k);
  // The body is serialised outside the lock (it can hold images); invalid UTF-8 in a client's instruction is
  // replaced rather than thrown on.
  const std::string body = record.dump(-1, ' ', false, Json::error_handler_t::replace);

  std::lock_guard lock(mu_);
  if (!time) time = utc_timestamp(SysClock::now());
  std::string line = "{\"seq\":" + std::to_string(next_seq_) +
                     ",\"time\":" + Json(*time).dump(-1, ' ', false, Json::error_handler_t::replace) + ",\"prev\":\"" +
                     prev_hash_ + "\"" + (body.size() > 2 ? "," + body.substr(1) : "}");
  const std::string hash = sha256_hex(line);
  line.push_back('\n');
  try {
    if (rotate_next_ || (file_->size > 0 && file_->size + line.size() > options_.max_file_bytes))
      open_file(file_index_ + 1);
  } catch (const Error& e) {
    io_error(e.what());
    return false;
  }
  ssize_t n;
  do n = ::write(file_->fd.fd, line.data(), line.size());
  while (n < 0 && errno == EINTR);
  if (n != ssize_t(line.size())) {
    const int err = n < 0 ? errno : ENOSPC;  // a short write on a regular file means the disk is full
    // Cut the partial line off so the next line starts clean; if that fails the file ends torn and is left behind.
    if (n > 0 && ::ftruncate(file_->fd.fd, off_t(file_->size)) != 0) rotate_next_ = true;
    io_error(file_->path + ": cannot write (" + std::strerror(err) + ")");
    return false;
  }
  file_->size += line.size();
  prev_hash_ = hash;
  ++next_seq_;
  ++lines_;
  dirty_ = true;
  if (options_.fsync == TraceOptions::Fsync::every_line) {
    if (::fdatasync(file_->fd.fd) != 0) io_error(file_->path + ": cannot fsync (" + std::strerror(errno) + ")");
    dirty_ = false;
  }
  return true;
}

void TraceRecorder::flush() {
  std::shared_ptr<File> file;
  {
    std::lock_guard lock(mu_);
    file = file_;
    dirty_ = false;
  }
  if (::fdatasync(file->fd.fd) != 0) io_error(file->path + ": cannot fsync (" + std::strerror(errno) + ")");
}

void TraceRecorder::sync_loop() {
  std::unique_lock lock(mu_);
  while (!stop_) {
    stop_cv_.wait_for(lock, std::chrono::milliseconds(options_.fsync_interval_ms), [this] { return stop_; });
    if (stop_ || !dirty_) continue;
    // Synced outside the lock so appends do not wait on the disk; the shared_ptr keeps the fd open through a rotation.
    const std::shared_ptr<File> file = file_;
    dirty_ = false;
    lock.unlock();
    if (::fdatasync(file->fd.fd) != 0) io_error(file->path + ": cannot fsync (" + std::strerror(errno) + ")");
    lock.lock();
  }
}

std::uint64_t TraceRecorder::lines_written() const { return lines_; }
std::uint64_t TraceRecorder::write_errors() const { return errors_; }

std::string TraceRecorder::current_file() const {
  std::lock_guard lock(mu_);
  return file_->path;
}

}  // namespace tether::runtime
