// Verbs of the `tether` binary: each registers its flags on the parser and runs after parsing.
#pragma once

#include <CLI/CLI.hpp>
#include <functional>

namespace tether::cli {

// Exit codes shared by every verb.
constexpr int kExitOk = 0, kExitCheckFailed = 1, kExitUsage = 2;

// A registered subcommand and what runs it once the command line has been parsed.
struct Verb {
  CLI::App* command;
  std::function<int()> run;
};

Verb add_predict(CLI::App& app);
Verb add_bench(CLI::App& app);
Verb add_serve(CLI::App& app);
Verb add_go(CLI::App& app);
Verb add_doctor(CLI::App& app);
Verb add_inspect(CLI::App& app);
Verb add_models(CLI::App& app);
Verb add_export(CLI::App& app);
Verb add_validate(CLI::App& app);
Verb add_traces(CLI::App& app);

// Path of a data file shipped with Tether (models/targets.json, ...); TETHER_DATA_DIR overrides the directory.
std::string data_file(const std::string& name);

}  // namespace tether::cli
