// util::run_process starts programs with an argument vector: no argument is ever seen by a shell.
#include <gtest/gtest.h>

#include <filesystem>
#include <unistd.h>

#include "piezo_compensation/util/child_process.h"

namespace fs = std::filesystem;
using piezo::util::command_line;
using piezo::util::run_process;

namespace {
fs::path fresh_dir(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("piezo_child_process_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}
}  // namespace

TEST(ChildProcess, ShellCharactersInArgumentsAreNotInterpreted) {
  const fs::path dir = fresh_dir("quote");
  const fs::path marker = dir / "pwned";
  // Through `sh -c "prog '<arg>'"` this argument would close the quote and create the marker.
  const std::string evil = "x'; touch '" + marker.string() + "'; echo '";
  const auto r = run_process({"/usr/bin/test", evil, "=", evil});
  EXPECT_TRUE(r.ok()) << r.error;
  EXPECT_FALSE(fs::exists(marker));
  const auto dollar = run_process({"/usr/bin/test", "$(touch " + marker.string() + ")", "=", "x"});
  EXPECT_TRUE(dollar.started);
  EXPECT_EQ(dollar.exit_code, 1);  // compared literally, not substituted
  EXPECT_FALSE(fs::exists(marker));
  fs::remove_all(dir);
}

TEST(ChildProcess, ExitStatusAndStartFailuresAreReported) {
  const auto ok = run_process({"/bin/true"});
  EXPECT_TRUE(ok.ok());
  EXPECT_TRUE(ok.error.empty());
  const auto fail = run_process({"/bin/false"});
  EXPECT_TRUE(fail.started);
  EXPECT_EQ(fail.exit_code, 1);
  EXPECT_NE(fail.error.find("exited with status 1"), std::string::npos) << fail.error;
  const auto missing = run_process({"/nonexistent/program"});
  EXPECT_FALSE(missing.ok());
  EXPECT_NE(missing.error.find("/nonexistent/program"), std::string::npos) << missing.error;
  EXPECT_FALSE(run_process({}).ok());
}

TEST(ChildProcess, CommandLineQuotesForReading) {
  EXPECT_EQ(command_line({"/usr/bin/python3", "a b", "it's", "plain-1.0"}),
            "/usr/bin/python3 'a b' 'it'\\''s' plain-1.0");
}
