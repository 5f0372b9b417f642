#include "piezo_compensation/nanocontrol/line_protocol.h"

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <stdexcept>

namespace piezo::nanocontrol {

namespace {
bool nc_printable(char c) { return c == '\t' || (c >= 0x20 && c <= 0x7E); }

void nc_set_error(std::string* error, const std::string& text) {
  if (error) *error = text;
}

std::string nc_shown(std::string_view text) {  // for messages: control bytes as \xNN, at most 40 characters
  std::string out;
  for (char c : text.substr(0, 40)) {
    if (c >= 0x20 && c <= 0x7E) {
      out += c;
    } else {
      static const char* hex = "0123456789ABCDEF";
      const auto u = static_cast<unsigned char>(c);
      out += "\\x";
      out += hex[u >> 4];
      out += hex[u & 15];
    }
  }
  if (text.size() > 40) out += "...";
  return out;
}
}  // namespace

const char* to_string(ReplyStatus status) {
  switch (status) {
    case ReplyStatus::kOk: return "o (ok)";
    case ReplyStatus::kError: return "e (error)";
    case ReplyStatus::kInfo: return "i (info)";
  }
  return "?";
}

std::optional<Reply> parse_reply(std::string_view line, std::string* error) {
  if (line.empty()) {
    nc_set_error(error, "empty reply line");
    return std::nullopt;
  }
  if (line.size() > kMaxLineBytes) {
    nc_set_error(error, "reply line longer than " + std::to_string(kMaxLineBytes) + " bytes");
    return std::nullopt;
  }
  Reply r;
  switch (line[0]) {
    case 'o': r.status = ReplyStatus::kOk; break;
    case 'e': r.status = ReplyStatus::kError; break;
    case 'i': r.status = ReplyStatus::kInfo; break;
    default:
      nc_set_error(error, "reply \"" + nc_shown(line) + "\" does not start with a status o, e or i");
      return std::nullopt;
  }
  if (line.size() > 1 && line[1] != '\t') {
    nc_set_error(error, "reply \"" + nc_shown(line) + "\": no tab after the status");
    return std::nullopt;
  }
  for (char c : line)
    if (!nc_printable(c)) {
      nc_set_error(error, "reply \"" + nc_shown(line) + "\" has a byte that is not printable ASCII");
      return std::nullopt;
    }
  if (line.size() > 2) r.message = std::string(line.substr(2));
  return r;
}

std::optional<std::array<std::int64_t, kChannelCount>> parse_four(std::string_view message, std::int64_t min,
                                                                   std::int64_t max, std::string* error) {
  std::array<std::int64_t, kChannelCount> out{};
  std::size_t pos = 0;
  int n = 0;
  while (pos < message.size()) {
    if (message[pos] == ' ' || message[pos] == '\t') {
      ++pos;
      continue;
    }
    std::size_t end = pos;
    while (end < message.size() && message[end] != ' ' && message[end] != '\t') ++end;
    const std::string token(message.substr(pos, end - pos));
    std::size_t digits = (token[0] == '-' || token[0] == '+') ? 1 : 0;
    bool numeric = token.size() > digits && token.size() <= digits + 15;
    for (std::size_t i = digits; numeric && i < token.size(); ++i) numeric = token[i] >= '0' && token[i] <= '9';
    if (!numeric) {
      nc_set_error(error, "\"" + nc_shown(token) + "\" in \"" + nc_shown(message) + "\" is not an integer");
      return std::nullopt;
    }
    if (n == kChannelCount) {
      nc_set_error(error, "more than four values in \"" + nc_shown(message) + "\"");
      return std::nullopt;
    }
    const std::int64_t v = std::strtoll(token.c_str(), nullptr, 10);
    if (v < min || v > max) {
      nc_set_error(error, "value " + token + " outside [" + std::to_string(min) + ", " + std::to_string(max) + "]");
      return std::nullopt;
    }
    out[n++] = v;
    pos = end;
  }
  if (n != kChannelCount) {
    nc_set_error(error, std::to_string(n) + " values in \"" + nc_shown(message) + "\", four expected");
    return std::nullopt;
  }
  return out;
}

char channel_letter(int index) { return index >= 0 && index < kChannelCount ? static_cast<char>('A' + index) : '?'; }

int channel_index(char letter) { return letter >= 'A' && letter < 'A' + kChannelCount ? letter - 'A' : -1; }

std::string set_fine16(char channel, int counts) {
  if (channel_index(channel) < 0) throw std::invalid_argument(std::string("channel '") + channel + "' is not A..D");
  if (counts < kFine16Min || counts > kFine16Max)
    throw std::invalid_argument("fine16 set point " + std::to_string(counts) + " outside [-32768, 32767]");
  return std::string("fine16 ") + channel + " " + std::to_string(counts);
}

std::string write_command(const std::string& command) {
  if (command.find_first_of("\r\n") != std::string::npos)
    throw std::invalid_argument("command \"" + nc_shown(command) + "\" contains a line break");
  return command + kTerminator;
}

void LineBuffer::append(const char* data, std::size_t size) {
  for (std::size_t i = 0; i < size; ++i) {
    const char c = data[i];
    if (c == '\n') continue;
    if (c == kTerminator) {
      if (overflowing_)
        overflowing_ = false;  // the end of the dropped line
      else
        lines_.push_back(std::move(partial_));
      partial_.clear();
      continue;
    }
    if (overflowing_) continue;
    partial_ += c;
    if (partial_.size() > kMaxLineBytes) {
      partial_.clear();
      overflowing_ = true;
      ++overflows_;
    }
  }
}

std::optional<std::string> LineBuffer::next_line() {
  if (head_ >= lines_.size()) return std::nullopt;
  std::string line = std::move(lines_[head_++]);
  if (head_ == lines_.size()) {
    lines_.clear();
    head_ = 0;
  }
  return line;
}

void LineBuffer::clear() {
  partial_.clear();
  lines_.clear();
  head_ = 0;
  overflowing_ = false;
}

std::optional<int> counts_for_voltage(double voltage_v, double counts_per_volt, double lo_v, double hi_v) {
  if (!std::isfinite(voltage_v) || !std::isfinite(counts_per_volt) || counts_per_volt <= 0) return std::nullopt;
  const double lo = std::max(lo_v * counts_per_volt, static_cast<double>(kFine16Min));
  const double hi = std::min(hi_v * counts_per_volt, static_cast<double>(kFine16Max));
  const double lo_count = std::ceil(lo - 1e-9), hi_count = std::floor(hi + 1e-9);
  if (lo_count > hi_count) return std::nullopt;
  double c = std::round(voltage_v * counts_per_volt);
  c = std::min(std::max(c, lo_count), hi_count);
  // the count must also be inside [lo_v, hi_v] as a voltage (the 1e-9 slack above is far below a count)
  if (c / counts_per_volt < lo_v - 1e-6 || c / counts_per_volt > hi_v + 1e-6) return std::nullopt;
  return static_cast<int>(c);
}

ReadStats read_stats(const std::vector<std::int64_t>& reads) {
  ReadStats s;
  s.count = static_cast<int>(reads.size());
  if (reads.empty()) return s;
  double sum = 0;
  for (auto r : reads) sum += static_cast<double>(r);
  s.mean = sum / s.count;
  if (s.count > 1) {
    double ss = 0;
    for (auto r : reads) ss += (r - s.mean) * (r - s.mean);
    s.sigma = std::sqrt(ss / (s.count - 1));
  }
  return s;
}

}  // namespace piezo::nanocontrol
