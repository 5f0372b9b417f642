// The Kleindiek NanoControl's serial line protocol, as far as the reference study's recording code shows it
// (docs/nanocontrol.md): ASCII commands ending in CR, each answered by one line "<status>\t<message>\r" with status
// o (ok), e (error, the message says why) or i (info, e.g. a piezo voltage breakdown). Pure: no I/O, no clocks.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace piezo::nanocontrol {

constexpr char kTerminator = '\r';
constexpr std::size_t kMaxLineBytes = 256;  // a longer line is garbage (the longest known reply is 4 counters)
constexpr int kChannelCount = 4;            // A..D; the MM3E uses three of them
constexpr int kFine16Min = -32768, kFine16Max = 32767;  // fine16 set point range (the study's ±80 V)

enum class ReplyStatus { kOk, kError, kInfo };
const char* to_string(ReplyStatus status);

struct Reply {
  ReplyStatus status = ReplyStatus::kOk;
  std::string message;
};

// One reply line without its CR. Accepts "o", "o\t<message>" (and e, i); the message is printable ASCII (tabs
// allowed). Anything else is garbled: nullopt and `error` says what was wrong.
std::optional<Reply> parse_reply(std::string_view line, std::string* error = nullptr);

// The message of `counterread` or `fine16 ?`: four integers separated by blanks. nullopt (with `error`) otherwise,
// or when a value is outside [min, max].
std::optional<std::array<std::int64_t, kChannelCount>> parse_four(std::string_view message, std::int64_t min,
                                                                   std::int64_t max, std::string* error = nullptr);

// Channel letter of an index 0..3 and back (-1 for anything else).
char channel_letter(int index);
int channel_index(char letter);

// Command texts, without the CR (write_command adds it).
std::string set_fine16(char channel, int counts);  // "fine16 C -1234"; std::invalid_argument outside the range
std::string write_command(const std::string& command);  // command + CR; std::invalid_argument for a CR/LF inside

// Collects bytes from the port into CR-terminated lines. A line longer than kMaxLineBytes is dropped whole (up to
// its CR) and counted; LF bytes are ignored (a terminal that sends CR LF).
class LineBuffer {
 public:
  void append(const char* data, std::size_t size);
  std::optional<std::string> next_line();  // the oldest complete line, without its CR
  void clear();
  bool has_partial() const { return !partial_.empty() || overflowing_; }
  std::uint64_t overflows() const { return overflows_; }

 private:
  std::string partial_;
  std::vector<std::string> lines_;
  std::size_t head_ = 0;
  bool overflowing_ = false;
  std::uint64_t overflows_ = 0;
};

// DAC counts of a voltage (counts_per_volt: the study's 32768 / 80 V = 409.6), rounded to the nearest count inside
// [lo_v, hi_v] and the fine16 range. nullopt when no count lies inside both.
std::optional<int> counts_for_voltage(double voltage_v, double counts_per_volt, double lo_v, double hi_v);

// Mean and sample standard deviation (n − 1; 0 for one value) of counter reads.
struct ReadStats {
  double mean = 0.0, sigma = 0.0;
  int count = 0;
};
ReadStats read_stats(const std::vector<std::int64_t>& reads);

}  // namespace piezo::nanocontrol
