// Subcommands of the `piezo` CLI register themselves here; main() dispatches on argv[1].
#pragma once

#include <functional>
#include <map>
#include <string>

namespace piezo::cli {

struct Command {
  std::string summary;                          // one line for `piezo --help`
  std::function<int(int argc, char** argv)> run;  // argv[0] is the subcommand name
};

std::map<std::string, Command>& registry();

struct Register {
  Register(const std::string& name, const std::string& summary, std::function<int(int, char**)> run) {
    registry()[name] = Command{summary, std::move(run)};
  }
};

}  // namespace piezo::cli
