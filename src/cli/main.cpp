// `piezo`: the one entry point for the offline tools. Each subcommand lives in src/cli/cmd_<name>.cpp.
#include <exception>
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/io/dataset.h"

namespace piezo::cli {
std::map<std::string, Command>& registry() {
  static std::map<std::string, Command> r;
  return r;
}
}  // namespace piezo::cli

namespace {
void usage(std::ostream& os) {
  os << "usage: piezo <command> [options]      (piezo <command> --help for its options)\n\ncommands:\n";
  for (const auto& [name, cmd] : piezo::cli::registry())
    os << "  " << name << std::string(name.size() < 12 ? 12 - name.size() : 1, ' ') << cmd.summary << "\n";
}
}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || std::string(argv[1]) == "--help" || std::string(argv[1]) == "-h" || std::string(argv[1]) == "help") {
    usage(argc < 2 ? std::cerr : std::cout);
    return argc < 2 ? 2 : 0;
  }
  auto& reg = piezo::cli::registry();
  auto it = reg.find(argv[1]);
  if (it == reg.end()) {
    std::cerr << "piezo: unknown command '" << argv[1] << "'\n";
    usage(std::cerr);
    return 2;
  }
  try {
    return it->second.run(argc - 1, argv + 1);
  } catch (const piezo::cli::UsageError& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 2;
  } catch (const piezo::io::DataError& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << "error: " << argv[1] << ": " << e.what() << "\n";
    return 1;
  }
}
