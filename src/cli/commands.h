// Verbs of the `tether` binary: each registers its flags on the parser and runs after parsing.
#pragma once

#include <CLI/CLI.hpp>
#include <functional>

namespace tether::cli {

// Exit codes shared by every verb.
constexpr int kExitOk = 0, kExitCheckFailed = 1, kExitUsage = 2;

// Adds the subcommand to `app`; the returned function runs it (called only when the subcommand was chosen).
std::function<int()> add_predict(CLI::App& app);
std::function<int()> add_bench(CLI::App& app);

}  // namespace tether::cli
