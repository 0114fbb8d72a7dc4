// Entry point of the `tether` binary: dispatches to one verb per file, maps errors to one-line messages.
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <iostream>
#include <string>

#include "cli/commands.h"
#include "core/error.h"

namespace {

// Last line of defence for an exception that escapes a thread (a server worker, an OpenMP region): the usual
// one-line error and exit code instead of std::terminate's abort and core dump.
[[noreturn]] void on_terminate() {
  std::string what = "unknown exception";
  if (const std::exception_ptr e = std::current_exception()) {
    try {
      std::rethrow_exception(e);
    } catch (const std::exception& ex) {
      what = ex.what();
    } catch (...) {
    }
  }
  std::fprintf(stderr, "error: internal: %s\n", what.c_str());
  std::_Exit(tether::cli::kExitCheckFailed);
}

}  // namespace

int main(int argc, char** argv) try {
  std::set_terminate(on_terminate);
  CLI::App app{"tether: deploy Vision-Language-Action robot policies"};
  app.require_subcommand(1);
  // Usage errors are one line, like every other error of the binary.
  app.failure_message(
      [](const CLI::App*, const CLI::Error& e) { return "error: " + std::string(e.what()) + " (see --help)\n"; });
  app.set_version_flag("--version", std::string("tether ") + TETHER_VERSION);
  const std::vector<tether::cli::Verb> verbs = {
      tether::cli::add_predict(app),
      tether::cli::add_bench(app),
      tether::cli::add_serve(app),
      tether::cli::add_go(app),
      tether::cli::add_doctor(app),
      tether::cli::add_inspect(app),
      tether::cli::add_models(app),
      tether::cli::add_export(app),
      tether::cli::add_validate(app),
      tether::cli::add_traces(app),
  };
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int rc = app.exit(e);
    return rc == 0 ? 0 : tether::cli::kExitUsage;
  }
  try {
    for (const auto& verb : verbs)
      if (verb.command->parsed()) return verb.run();
  } catch (const tether::Error& e) {
    std::cerr << "error: " << e.what() << "\n";
    return e.code() == tether::ErrorCode::internal ? tether::cli::kExitCheckFailed : tether::cli::kExitUsage;
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    return tether::cli::kExitCheckFailed;
  }
  return tether::cli::kExitUsage;
} catch (const std::exception& e) {  // while setting up the verbs, before any of them runs
  std::cerr << "error: " << e.what() << "\n";
  return tether::cli::kExitCheckFailed;
}
