#include "piezo_compensation/ros/nanocontrol_params.h"

#include <cmath>
#include <stdexcept>

#include "piezo_compensation/nanocontrol/serial_port.h"

namespace piezo::mm3e {

namespace {
params::ParamDef nc_channels_param() {
  return params::text("channels", "ABC", "NanoControl channel of axis a, b, c (nanocontrol only)")
      .rule("three different letters of A..D");
}
params::ParamDef nc_scale_param() {
  return params::numbers("nm_per_count", "nm", {20.0, 20.0, -20.0}, -1e6, 1e6, 3, 3,
                         "encoder counter scale of axis a, b, c with its sign (nanocontrol only; c falls as it rises)")
      .rule("no entry 0");
}
params::ParamDef nc_dac_param() {
  return params::number("counts_per_volt", "counts/V", 409.6, 1.0, 1e6,
                        "fine16 DAC counts per volt: 32768 / 80 V (nanocontrol only)");
}

std::array<char, 3> nc_read_channels(params::ParamReader& r) {
  const std::string text = r.text("channels");
  std::array<char, 3> c{};
  bool ok = text.size() == 3;
  for (int i = 0; ok && i < 3; ++i) {
    c[i] = text[i];
    ok = nanocontrol::channel_index(c[i]) >= 0;
    for (int j = 0; ok && j < i; ++j) ok = c[i] != c[j];
  }
  if (!ok)
    throw std::invalid_argument("parameter " + r.resolved("channels") + " = \"" + text +
                                "\": three different letters of A, B, C, D (channel of axis a, b, c)");
  return c;
}

std::array<double, 3> nc_read_scale(params::ParamReader& r) {
  const std::vector<double> v = r.numbers("nm_per_count");
  std::array<double, 3> s{};
  for (int i = 0; i < 3; ++i) {
    if (v[i] == 0.0) throw std::invalid_argument("parameter " + r.resolved("nm_per_count") + ": an entry is 0 nm");
    s[i] = v[i];
  }
  return s;
}
}  // namespace

std::vector<params::ParamDef> nanocontrol_driver_params() {
  using namespace params;
  return {
      text("port", "/dev/ttyUSB0", "serial port of the manipulator's NanoControl (nanocontrol only)"),
      integer("baud", "baud", 115200, 9600, 921600, "serial speed, 8N1 (nanocontrol only)")
          .rule("a termios speed: 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600"),
      number("reply_timeout_s", "s", 0.2, 0.001, 10.0,
             "a reply not complete by then is a timeout: the command counts as not done (nanocontrol only)"),
      nc_channels_param(),
      nc_scale_param(),
      nc_dac_param(),
      integer("counter_reads", "reads", 5, 1, 100, "counterread commands per sample: their mean and σ (nanocontrol only)"),
      number("min_sample_period_s", "s", 0.05, 0.0, 60.0,
             "a sample starts at least this long after the previous one; the controller's replies set the rate "
             "above it (nanocontrol only)"),
  };
}

std::vector<params::ParamDef> nanocontrol_sim_params() {
  using namespace params;
  return {
      text("port", "/tmp/mm3e_sim_nanocontrol",
           "nanocontrol: the symbolic link to the pseudo-terminal the simulated controller answers on (the "
           "driver's ~port)")
          .rule("not an existing non-link file"),
      nc_channels_param(),
      nc_scale_param(),
      nc_dac_param(),
      number("reply_delay_s", "s", 0.016, 0.0, 1.0,
             "nanocontrol: the controller's time from a command to its reply (the study: 6 exchanges in 0.096 s)"),
  };
}

nanocontrol::LinkOptions read_link_options(params::ParamReader& r, double min_voltage_v, double max_voltage_v,
                                           bool check) {
  nanocontrol::LinkOptions o;
  o.port = r.text("port");
  o.baud = r.integer("baud");
  o.reply_timeout_s = r.number("reply_timeout_s");
  o.channels = nc_read_channels(r);
  o.nm_per_count = nc_read_scale(r);
  o.counts_per_volt = r.number("counts_per_volt");
  o.counter_reads = r.integer("counter_reads");
  o.min_sample_period_s = r.number("min_sample_period_s");
  o.min_voltage_v = min_voltage_v;
  o.max_voltage_v = max_voltage_v;
  if (!check) return o;
  if (o.port.empty()) throw std::invalid_argument("parameter " + r.resolved("port") + " is empty");
  if (!nanocontrol::supported_baud(o.baud))
    throw std::invalid_argument("parameter " + r.resolved("baud") + " = " + std::to_string(o.baud) +
                                " is not a termios speed (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)");
  const double reach_v = 32768.0 / o.counts_per_volt;
  if (min_voltage_v < -reach_v - 1e-9 || max_voltage_v > reach_v + 1e-9)
    throw std::invalid_argument("parameters " + r.resolved("min_voltage_v") + " / max_voltage_v: [" +
                                std::to_string(min_voltage_v) + ", " + std::to_string(max_voltage_v) +
                                "] V reaches beyond the fine16 range ±" + std::to_string(reach_v) +
                                " V at counts_per_volt " + std::to_string(o.counts_per_volt));
  nanocontrol::validate(o);
  return o;
}

nanocontrol::SimDeviceConfig read_sim_device(params::ParamReader& r, double initial_voltage_v) {
  nanocontrol::SimDeviceConfig c;
  c.channels = nc_read_channels(r);
  c.nm_per_count = nc_read_scale(r);
  c.counts_per_volt = r.number("counts_per_volt");
  c.initial_voltage_v = initial_voltage_v;
  return c;
}

void diagnose_link(const nanocontrol::LinkMonitor::Snapshot& s, const nanocontrol::LinkCounters& previous,
                   diagnostic_updater::DiagnosticStatusWrapper& stat) {
  using diagnostic_msgs::DiagnosticStatus;
  const nanocontrol::LinkCounters& c = s.counters;
  stat.summary(DiagnosticStatus::OK, "ok");
  if (c.breakdown) stat.mergeSummary(DiagnosticStatus::ERROR, "breakdown: " + c.last_info + "; every axis held until ~recover");
  // a fault since the previous update is a WARN naming it; the counters and the last of each stay as values
  if (c.refused > previous.refused) stat.mergeSummary(DiagnosticStatus::WARN, "refused: " + c.last_refusal);
  if (c.timeouts > previous.timeouts) stat.mergeSummary(DiagnosticStatus::WARN, "timeout: " + c.last_timeout);
  if (c.garbled > previous.garbled) stat.mergeSummary(DiagnosticStatus::WARN, "garbled: " + c.last_garbled);
  stat.add("version", s.version);
  stat.add("exchanges", c.exchanges);
  stat.add("replies ok", c.ok);
  stat.add("refused (e)", c.refused);
  stat.add("last refusal", c.last_refusal);
  stat.add("info (i)", c.infos);
  stat.add("breakdowns", c.breakdowns);
  stat.add("last info", c.last_info);
  stat.add("breakdown latched", c.breakdown);
  stat.add("timeouts", c.timeouts);
  stat.add("last timeout", c.last_timeout);
  stat.add("garbled replies", c.garbled);
  stat.add("last garbled", c.last_garbled);
  stat.add("samples", c.samples);
  stat.add("samples dropped", c.samples_dropped);
  stat.add("sample period [s]", s.sample_period_s);
  stat.add("sample duration [s]", s.sample_duration_s);
  for (int i = 0; i < 3; ++i) {
    const std::string axis(1, static_cast<char>('a' + i));
    stat.add("reading sigma " + axis + " [m]", s.sigma_m[i]);
  }
}

}  // namespace piezo::mm3e
