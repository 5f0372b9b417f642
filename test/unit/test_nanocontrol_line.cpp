// The NanoControl line codec: reply lines, the four-value messages, the line buffer, DAC counts within limits,
// read statistics.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "piezo_compensation/nanocontrol/line_protocol.h"

using namespace piezo::nanocontrol;

TEST(NanoControlLine, ParsesTheThreeStatuses) {
  auto ok = parse_reply("o\t12 3 -4 0");
  ASSERT_TRUE(ok);
  EXPECT_EQ(ok->status, ReplyStatus::kOk);
  EXPECT_EQ(ok->message, "12 3 -4 0");
  auto err = parse_reply("e\tvalue out of range");
  ASSERT_TRUE(err);
  EXPECT_EQ(err->status, ReplyStatus::kError);
  EXPECT_EQ(err->message, "value out of range");
  auto info = parse_reply("i\tPiezo Voltage Breakdown");
  ASSERT_TRUE(info);
  EXPECT_EQ(info->status, ReplyStatus::kInfo);
  // a bare status, or status and tab: an empty message (the study's code takes line[2:-1])
  auto bare = parse_reply("o");
  ASSERT_TRUE(bare);
  EXPECT_EQ(bare->message, "");
  auto tab = parse_reply("o\t");
  ASSERT_TRUE(tab);
  EXPECT_EQ(tab->message, "");
}

TEST(NanoControlLine, MalformedRepliesAreRejectedWithAReason) {
  struct Case {
    std::string line, reason;
  } cases[] = {
      {"", "empty"},
      {"x\tfoo", "does not start with a status"},
      {"O\t1", "does not start with a status"},
      {"ok", "no tab after the status"},
      {std::string("o\t1\x01 2"), "not printable"},
      {std::string("o\t\xfe"), "not printable"},
      {"o\t" + std::string(300, '1'), "longer than"},
  };
  for (const auto& c : cases) {
    std::string error;
    EXPECT_FALSE(parse_reply(c.line, &error)) << c.line;
    EXPECT_NE(error.find(c.reason), std::string::npos) << "'" << error << "' for " << c.line;
  }
}

TEST(NanoControlLine, FourValues) {
  auto v = parse_four("12 -3  4 0", -100, 100);
  ASSERT_TRUE(v);
  EXPECT_EQ((*v)[0], 12);
  EXPECT_EQ((*v)[1], -3);
  EXPECT_EQ((*v)[2], 4);
  EXPECT_EQ((*v)[3], 0);
  std::string error;
  EXPECT_FALSE(parse_four("1 2 3", -100, 100, &error));
  EXPECT_NE(error.find("3 values"), std::string::npos) << error;
  EXPECT_FALSE(parse_four("1 2 3 4 5", -100, 100, &error));
  EXPECT_NE(error.find("more than four"), std::string::npos) << error;
  EXPECT_FALSE(parse_four("1 2 x 4", -100, 100, &error));
  EXPECT_NE(error.find("not an integer"), std::string::npos) << error;
  EXPECT_FALSE(parse_four("1 2 3.5 4", -100, 100, &error));
  EXPECT_FALSE(parse_four("1 2 - 4", -100, 100, &error));
  EXPECT_FALSE(parse_four("1 2 3 40000", -32768, 32767, &error));
  EXPECT_NE(error.find("outside"), std::string::npos) << error;
  EXPECT_FALSE(parse_four("", -100, 100, &error));
  EXPECT_FALSE(parse_four("1 2 3 99999999999999999999", INT64_MIN, INT64_MAX, &error));
}

TEST(NanoControlLine, Commands) {
  EXPECT_EQ(set_fine16('C', -1234), "fine16 C -1234");
  EXPECT_EQ(set_fine16('A', 32767), "fine16 A 32767");
  EXPECT_THROW(set_fine16('C', 32768), std::invalid_argument);
  EXPECT_THROW(set_fine16('C', -32769), std::invalid_argument);
  EXPECT_THROW(set_fine16('E', 0), std::invalid_argument);
  EXPECT_EQ(write_command("counterread"), "counterread\r");
  EXPECT_THROW(write_command("fine16 C 1\rfine16 C 2"), std::invalid_argument);
  EXPECT_EQ(channel_index('D'), 3);
  EXPECT_EQ(channel_index('a'), -1);
  EXPECT_EQ(channel_letter(2), 'C');
}

TEST(NanoControlLine, LineBufferSplitsJoinsAndDropsOverlongLines) {
  LineBuffer b;
  b.append("o\t1 2", 5);
  EXPECT_FALSE(b.next_line());
  EXPECT_TRUE(b.has_partial());
  b.append(" 3 4\r\ne\tno\r", 11);
  EXPECT_EQ(*b.next_line(), "o\t1 2 3 4");
  EXPECT_EQ(*b.next_line(), "e\tno");
  EXPECT_FALSE(b.next_line());
  const std::string huge(kMaxLineBytes + 10, 'x');
  b.append(huge.data(), huge.size());
  b.append("yy\ro\t\r", 6);
  EXPECT_EQ(b.overflows(), 1u);
  EXPECT_EQ(*b.next_line(), "o\t");  // the overlong line is dropped whole, up to its CR
  EXPECT_FALSE(b.next_line());
  b.append("partial", 7);
  b.clear();
  b.append("\r", 1);
  EXPECT_EQ(*b.next_line(), "");
}

TEST(NanoControlLine, CountsStayInsideTheLimitsAndTheDac) {
  const double cpv = 409.6;
  EXPECT_EQ(*counts_for_voltage(0.0, cpv, -80, 80), 0);
  EXPECT_EQ(*counts_for_voltage(12.5, cpv, -80, 80), 5120);
  EXPECT_EQ(*counts_for_voltage(80.0, cpv, -80, 80), 32767);   // the DAC's top, just below 80 V
  EXPECT_EQ(*counts_for_voltage(-80.0, cpv, -80, 80), -32768);
  // the nearest count above a limit is not taken: the one inside is
  const double lim = 10.001;  // 4096.41 counts
  const int c = *counts_for_voltage(lim, cpv, -lim, lim);
  EXPECT_EQ(c, 4096);
  EXPECT_LE(c / cpv, lim);
  const int up = *counts_for_voltage(10.0012, cpv, -80, 10.0012);  // 4096.49 → 4096
  EXPECT_LE(up / cpv, 10.0012);
  const int round_up = *counts_for_voltage(10.0023, cpv, -80, 10.0023);  // 4096.94 would round to 4097 > limit
  EXPECT_EQ(round_up, 4096);
  EXPECT_FALSE(counts_for_voltage(std::nan(""), cpv, -80, 80));
  EXPECT_FALSE(counts_for_voltage(1.0, cpv, 1.0001, 1.0002));  // no count between 409.64 and 409.68
  EXPECT_FALSE(counts_for_voltage(100.0, cpv, 90, 100));       // beyond the DAC
}

TEST(NanoControlLine, ReadStats) {
  const ReadStats s = read_stats({10, 12, 11, 13, 9});
  EXPECT_EQ(s.count, 5);
  EXPECT_DOUBLE_EQ(s.mean, 11.0);
  EXPECT_NEAR(s.sigma, std::sqrt(2.5), 1e-12);
  EXPECT_DOUBLE_EQ(read_stats({7}).sigma, 0.0);
  EXPECT_EQ(read_stats({}).count, 0);
}
