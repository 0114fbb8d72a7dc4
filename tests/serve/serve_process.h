// The real `tether serve` (or `tether go`) as a child process on a free port: its listening line parsed, SIGTERM and
// the exit status, SIGKILL if a test leaves it running. Shared by the process tests.
#pragma once

#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <map>
#include <regex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "http_test_client.h"

extern char** environ;

namespace tether::serve::testing {

// A `tether serve` child whose stdout is read for the listening line. SIGKILLed if a test leaves it running.
class ServeProcess {
 public:
  // `verb_args`: what follows the binary, e.g. {"serve", DIR, "--port", "0"}.
  // `stderr_file`: where the child's stderr goes (inherited when empty).
  explicit ServeProcess(std::vector<std::string> verb_args, const std::vector<std::string>& env_overrides = {},
                        const std::string& stderr_file = "") {
    int out[2];
    if (pipe(out) != 0) throw std::runtime_error("pipe failed");
    std::vector<std::string> args = {TETHER_BINARY};
    args.insert(args.end(), verb_args.begin(), verb_args.end());
    std::vector<std::string> env_strings;
    // An override replaces the inherited variable (getenv would find the first of two).
    const auto overridden = [&](const std::string& entry) {
      const std::string name = entry.substr(0, entry.find('=') + 1);
      for (const auto& o : env_overrides)
        if (o.compare(0, name.size(), name) == 0) return true;
      return false;
    };
    for (char** e = environ; *e; ++e)
      if (!overridden(*e)) env_strings.emplace_back(*e);
    env_strings.insert(env_strings.end(), env_overrides.begin(), env_overrides.end());
    std::vector<char*> envp;
    for (auto& e : env_strings) envp.push_back(e.data());
    envp.push_back(nullptr);
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_adddup2(&fa, out[1], STDOUT_FILENO);
    posix_spawn_file_actions_addclose(&fa, out[0]);
    if (!stderr_file.empty())
      posix_spawn_file_actions_addopen(&fa, STDERR_FILENO, stderr_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (posix_spawn(&pid_, argv[0], &fa, nullptr, argv.data(), envp.data()) != 0) throw std::runtime_error("spawn failed");
    posix_spawn_file_actions_destroy(&fa);
    close(out[1]);
    out_ = fdopen(out[0], "r");
    // One line per transport besides HTTP, then the HTTP line.
    for (char line[512];;) {
      if (!fgets(line, sizeof line, out_)) throw std::runtime_error("tether serve printed no listening line");
      std::smatch m;
      const std::string s(line);
      if (std::regex_search(s, m, std::regex(R"(^tether serve: (\S+) listening on 127\.0\.0\.1:(\d+)\n$)"))) {
        transport_ports_[m[1]] = uint16_t(std::stoi(m[2]));
        continue;
      }
      if (!std::regex_search(s, m, std::regex(R"(^tether serve: listening on http://127\.0\.0\.1:(\d+)\n$)")))
        throw std::runtime_error("unexpected line: " + s);
      port_ = uint16_t(std::stoi(m[1]));
      break;
    }
  }
  ~ServeProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
    if (out_) fclose(out_);
  }
  uint16_t port() const { return port_; }
  // The port of a transport besides HTTP (openpi, gr00t, zmq); 0 if it was not started.
  uint16_t transport_port(const std::string& name) const {
    const auto it = transport_ports_.find(name);
    return it == transport_ports_.end() ? 0 : it->second;
  }
  // SIGTERM, then the exit status (or -1 if it did not exit normally within 30 s).
  int terminate() {
    kill(pid_, SIGTERM);
    for (int i = 0; i < 3000; ++i) {
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return -1;
  }

 private:
  pid_t pid_ = -1;
  FILE* out_ = nullptr;
  uint16_t port_ = 0;
  std::map<std::string, uint16_t> transport_ports_;
};

inline void wait_ready(uint16_t port) {
  for (int i = 0; i < 600; ++i) {
    if (http_get(port, "/health").status == 200) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  FAIL() << "/health never turned 200";
}

}  // namespace tether::serve::testing
