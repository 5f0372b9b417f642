// Starting another program without a shell: the arguments go to posix_spawn as a vector, so no character in a
// path or option (quotes, ;, $, spaces) is ever interpreted.
#pragma once

#include <string>
#include <vector>

namespace piezo::util {

struct ChildResult {
  bool started = false;  // false: the program could not be started (error says why)
  int exit_code = -1;    // its exit status; -1 when it was ended by a signal
  std::string error;     // empty on exit code 0
  bool ok() const { return started && exit_code == 0; }
};

// Runs argv[0] (a path, or a name looked up in PATH when it has no '/') with argv, inheriting stdin, stdout,
// stderr and the environment, and waits for it.
ChildResult run_process(const std::vector<std::string>& argv);

// The command for messages, each argument quoted where a shell would need it (for reading, never executed).
std::string command_line(const std::vector<std::string>& argv);

}  // namespace piezo::util
