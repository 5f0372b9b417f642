#include "piezo_compensation/nanocontrol/sim_device.h"

#include <cmath>
#include <sstream>
#include <stdexcept>
#include <vector>

namespace piezo::nanocontrol {

const char* to_string(SimFault fault) {
  switch (fault) {
    case SimFault::kErrorReply: return "e reply to the next set point";
    case SimFault::kBreakdown: return "i breakdown reply to the next command";
    case SimFault::kLostReply: return "no reply to the next command";
    case SimFault::kGarbled: return "garbled reply to the next command";
    case SimFault::kPartial: return "partial reply (no CR) to the next command";
  }
  return "?";
}

namespace {
std::vector<std::string> nc_words(const std::string& line) {
  std::istringstream in(line);
  std::vector<std::string> w;
  for (std::string s; in >> s;) w.push_back(s);
  return w;
}

bool nc_integer(const std::string& s, long long& v) {
  if (s.empty() || s.size() > 12) return false;
  std::size_t i = (s[0] == '-' || s[0] == '+') ? 1 : 0;
  if (i == s.size()) return false;
  for (std::size_t k = i; k < s.size(); ++k)
    if (s[k] < '0' || s[k] > '9') return false;
  v = std::stoll(s);
  return true;
}
}  // namespace

SimDevice::SimDevice(const SimDeviceConfig& config, SimPlant plant) : config_(config), plant_(std::move(plant)) {
  if (!plant_) throw std::invalid_argument("SimDevice: no plant");
  if (!(config_.counts_per_volt > 0)) throw std::invalid_argument("counts_per_volt must be > 0");
  for (int i = 0; i < 3; ++i) {
    if (channel_index(config_.channels[i]) < 0) throw std::invalid_argument("channels must be A..D");
    if (config_.nm_per_count[i] == 0.0 || !std::isfinite(config_.nm_per_count[i]))
      throw std::invalid_argument("nm_per_count must be finite and non-zero");
  }
  const long long c = std::llround(config_.initial_voltage_v * config_.counts_per_volt);
  if (c < kFine16Min || c > kFine16Max) throw std::invalid_argument("initial_voltage_v is outside the fine16 range");
  fine16_.fill(static_cast<int>(c));
}

void SimDevice::inject(SimFault fault) {
  if (fault == SimFault::kErrorReply)
    error_next_set_point_ = true;
  else
    next_ = fault;
}

int SimDevice::axis_of(int channel) const {
  for (int i = 0; i < 3; ++i)
    if (channel_index(config_.channels[i]) == channel) return i;
  return -1;
}

std::array<double, kChannelCount> SimDevice::voltages_v() const {
  std::array<double, kChannelCount> v{};
  for (int c = 0; c < kChannelCount; ++c) v[c] = fine16_[c] / config_.counts_per_volt;
  return v;
}

void SimDevice::advance(double now_s) {
  if (!started_) {
    started_ = true;
    time_s_ = now_s;
  }
  const double dt = now_s - time_s_;
  if (dt <= 0 && last_) return;
  std::array<double, 3> v{};
  const auto all = voltages_v();
  for (int i = 0; i < 3; ++i) v[i] = all[channel_index(config_.channels[i])];
  last_ = plant_(v, std::max(dt, 1e-6));
  time_s_ = std::max(now_s, time_s_);
}

std::string SimDevice::counters_text() {
  std::ostringstream os;
  for (int c = 0; c < kChannelCount; ++c) {
    const int axis = axis_of(c);
    std::int64_t count = 0;
    if (axis >= 0 && last_) count = std::llround(last_->axes[axis].measured_position_nm / config_.nm_per_count[axis]);
    os << (c ? " " : "") << count - counter_offset_[c];
  }
  return os.str();
}

std::string SimDevice::reply(const std::string& line) {
  const std::vector<std::string> w = nc_words(line);
  if (w.empty()) return "e\tempty command";
  const std::string& cmd = w[0];
  if (cmd == "version" && w.size() == 1) return "o\t" + config_.version;
  if (cmd == "knbus" && w.size() == 2 && w[1] == "?") return "o\t1 0 0";
  if (cmd == "stop" && w.size() == 1) return "o\t";
  if (cmd == "counterread" && w.size() == 1) {
    for (int i = 0; i < 3 && last_; ++i) truth_sum_nm_[i] += last_->axes[i].true_position_nm;
    ++truth_reads_;
    return "o\t" + counters_text();
  }
  if (cmd == "counterreset" && w.size() == 1) {
    counter_offset_.fill(0);
    const std::string now = counters_text();
    std::istringstream in(now);
    for (auto& o : counter_offset_) in >> o;
    return "o\t";
  }
  if ((cmd == "fine16" || cmd == "fineu") && w.size() == 2 && w[1] == "?") {
    if (truth_reads_ > 0) {
      answer_->sample_closed = true;
      for (int i = 0; i < 3; ++i) answer_->sample_truth_nm[i] = truth_sum_nm_[i] / truth_reads_;
      truth_sum_nm_.fill(0.0);
      truth_reads_ = 0;
    }
    std::ostringstream os;
    for (int c = 0; c < kChannelCount; ++c)
      os << (c ? " " : "")
         << (cmd == "fine16" ? fine16_[c] : std::llround(fine16_[c] * 1000.0 / config_.counts_per_volt));
    return "o\t" + os.str();
  }
  const int channel = w.size() >= 2 && w[1].size() == 1 ? channel_index(w[1][0]) : -1;
  if ((cmd == "fine16" || cmd == "fineu") && w.size() == 3 && channel >= 0) {
    if (w[2] == "?") {
      const int c = fine16_[channel];
      return "o\t" + std::to_string(cmd == "fine16" ? c : std::llround(c * 1000.0 / config_.counts_per_volt));
    }
    long long v = 0;
    if (!nc_integer(w[2], v)) return "e\tnot a number: " + w[2];
    const long long counts = cmd == "fine16" ? v : std::llround(v / 1000.0 * config_.counts_per_volt);
    if ((cmd == "fine16" && (v < kFine16Min || v > kFine16Max)) || (cmd == "fineu" && std::llabs(v) > 80000))
      return "e\tvalue out of range: " + w[2];
    if (error_next_set_point_) {
      error_next_set_point_ = false;
      return "e\tset point refused (injected fault)";
    }
    if (next_ == SimFault::kBreakdown) return "i\tPiezo Voltage Breakdown";  // not applied
    fine16_[channel] = static_cast<int>(std::min<long long>(std::max<long long>(counts, kFine16Min), kFine16Max));
    answer_->set_point = true;
    answer_->axis = axis_of(channel);
    answer_->voltage_v = fine16_[channel] / config_.counts_per_volt;
    return "o\t";
  }
  return "e\tunknown command: " + line.substr(0, 40);
}

SimDevice::Answer SimDevice::handle(const std::string& line, double now_s) {
  ++commands_;
  Answer a;
  advance(now_s);  // the old voltages held until now; the new ones from now on
  answer_ = &a;
  std::string text = reply(line);
  answer_ = nullptr;
  const std::optional<SimFault> fault = next_;
  next_.reset();
  if (!fault || *fault == SimFault::kBreakdown) {
    if (fault) text = "i\tPiezo Voltage Breakdown";
    a.bytes = text + kTerminator;
    return a;
  }
  switch (*fault) {
    case SimFault::kLostReply: break;
    case SimFault::kGarbled: a.bytes = std::string("\x15o#\xfe") + "12 -7?" + kTerminator; break;
    case SimFault::kPartial: a.bytes = text.substr(0, std::max<std::size_t>(1, text.size() / 2)); break;
    default: break;
  }
  return a;
}

}  // namespace piezo::nanocontrol
