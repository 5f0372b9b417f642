// The CLI option parser: durations with units and plain seconds.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "../../src/cli/args.h"

namespace {

using piezo::cli::Args;
using piezo::cli::UsageError;

double parse(const std::string& value) {
  Args a("test", "duration parsing");
  a.option("duration", "T", "a duration");
  std::vector<std::string> words{"piezo", "--duration", value};
  std::vector<char*> argv;
  for (auto& w : words) argv.push_back(w.data());
  a.parse(static_cast<int>(argv.size()), argv.data());
  return a.seconds("duration");
}

TEST(CliArgs, DurationUnits) {
  EXPECT_DOUBLE_EQ(parse("26h"), 26 * 3600.0);
  EXPECT_DOUBLE_EQ(parse("90min"), 5400.0);
  EXPECT_DOUBLE_EQ(parse("30s"), 30.0);
  EXPECT_DOUBLE_EQ(parse("2d"), 172800.0);
  EXPECT_DOUBLE_EQ(parse("1.5h"), 5400.0);
}

TEST(CliArgs, DurationPlainSeconds) {
  EXPECT_DOUBLE_EQ(parse("90"), 90.0);
  EXPECT_DOUBLE_EQ(parse("2.5"), 2.5);
  EXPECT_DOUBLE_EQ(parse("1e3"), 1000.0);
}

TEST(CliArgs, DurationRejectsGarbageNamingTheOption) {
  for (const char* bad : {"", "h", "26 h", "26hours", "10m", "abc", "nan", "inf", "5sec"}) {
    try {
      parse(bad);
      ADD_FAILURE() << "accepted '" << bad << "'";
    } catch (const UsageError& e) {
      EXPECT_NE(std::string(e.what()).find("--duration"), std::string::npos) << e.what();
    }
  }
}

}  // namespace
