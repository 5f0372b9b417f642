// The controller-log import: reads averaged per set point, temperature repaired and counted (io/controller_log.h).
#include "piezo_compensation/io/controller_log.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string_view>
#include <vector>

#include "piezo_compensation/io/axes.h"

namespace piezo::io {

namespace {

std::vector<std::string_view> split_cells(std::string_view line) {
  std::vector<std::string_view> out;
  std::size_t start = 0;
  while (true) {
    const std::size_t comma = line.find(',', start);
    std::string_view cell = line.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start);
    while (!cell.empty() && (cell.front() == ' ' || cell.front() == '\t')) cell.remove_prefix(1);
    while (!cell.empty() && (cell.back() == ' ' || cell.back() == '\t' || cell.back() == '\r')) cell.remove_suffix(1);
    out.push_back(cell);
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  return out;
}

bool is_nan_text(std::string_view s) { return s.empty() || s == "NaN" || s == "nan" || s == "NAN" || s == "-nan"; }

// Which controller-log column each cell goes to.
struct LogColumns {
  int setpoint = -1, time = -1, temperature = -1, mean = -1;
  std::vector<int> reads;  // <axis>_0, <axis>_1, … in order
  std::size_t width = 0;
};

LogColumns map_columns(const std::vector<std::string_view>& names, const std::string& path, const std::string& axis) {
  LogColumns c;
  c.width = names.size();
  std::vector<std::pair<int, int>> reads;  // (read index, column)
  for (std::size_t k = 0; k < names.size(); ++k) {
    const std::string n(names[k]);
    const int col = static_cast<int>(k);
    if (n == "finestep") c.setpoint = col;
    else if (n == "time") c.time = col;
    else if (n == "temp") c.temperature = col;
    else if (n == axis + "_mean") c.mean = col;
    else if (n.empty() && k == 0) continue;  // a pandas index column
    else if (n.size() > axis.size() + 1 && n.compare(0, axis.size() + 1, axis + "_") == 0 &&
             std::all_of(n.begin() + static_cast<long>(axis.size()) + 1, n.end(), [](char ch) { return ch >= '0' && ch <= '9'; })) {
      const std::string digits = n.substr(axis.size() + 1);
      if (digits.size() > 3)
        throw DataError(path + ": row 1, column " + n + ": a read index over 999 (the reads are numbered from 0)");
      const int index = std::stoi(digits);
      for (const auto& r : reads)
        if (r.first == index) throw DataError(path + ": row 1, column " + n + ": the read numbered twice");
      reads.emplace_back(index, col);
    } else
      throw DataError(path + ": row 1, column " + (n.empty() ? "#" + std::to_string(k + 1) : n) +
                      ": not a controller-log column for axis " + axis + " (finestep, time, " + axis + "_0…, temp, " +
                      axis + "_mean)");
  }
  if (c.setpoint < 0) throw DataError(path + ": missing column finestep (the DAC set point)");
  if (c.time < 0) throw DataError(path + ": missing column time (the host clock); a log without timestamps cannot be imported");
  std::sort(reads.begin(), reads.end());
  for (std::size_t k = 0; k < reads.size(); ++k) {
    if (reads[k].first != static_cast<int>(k))
      throw DataError(path + ": missing column " + axis + "_" + std::to_string(k) + " (the reads are numbered from 0)");
    c.reads.push_back(reads[k].second);
  }
  if (c.reads.empty()) throw DataError(path + ": missing column " + axis + "_0 (no encoder reads of axis " + axis + ")");
  return c;
}

double number(std::string_view cell, bool nan_ok, const std::string& path, std::size_t row, std::string_view column) {
  if (nan_ok && is_nan_text(cell)) return NAN;
  double v = 0;
  const auto [p, ec] = std::from_chars(cell.data(), cell.data() + cell.size(), v);
  if (ec != std::errc() || p != cell.data() + cell.size() || !std::isfinite(v))
    throw DataError(path + ": row " + std::to_string(row) + ", column " + std::string(column) + ": " +
                    (cell.empty() ? std::string("empty cell") : "not a number: '" + std::string(cell) + "'"));
  return v;
}

// The temperature column with every bad cell replaced by the last good reading (the first good one before it),
// or empty when too few cells are good to keep it.
std::vector<double> repair_temperature(const std::vector<double>& t, const ControllerLogOptions& o, ControllerLogReport& r) {
  std::vector<double> in_range;
  for (double x : t)
    if (std::isfinite(x) && x >= o.temperature_min_c && x <= o.temperature_max_c) in_range.push_back(x);
  std::vector<char> good(t.size(), 0);
  if (!in_range.empty()) {
    std::nth_element(in_range.begin(), in_range.begin() + static_cast<long>(in_range.size() / 2), in_range.end());
    double last = in_range[in_range.size() / 2];  // the reference a first reading is judged against
    for (std::size_t i = 0; i < t.size(); ++i) {
      if (!std::isfinite(t[i])) ++r.temperature_nan;
      else if (t[i] < o.temperature_min_c || t[i] > o.temperature_max_c) ++r.temperature_out_of_range;
      else if (std::fabs(t[i] - last) > o.temperature_max_step_c) ++r.temperature_jumps;
      else good[i] = 1, last = t[i];
    }
  } else {
    for (double x : t) ++(std::isfinite(x) ? r.temperature_out_of_range : r.temperature_nan);
  }
  const auto n_good = static_cast<std::size_t>(std::count(good.begin(), good.end(), 1));
  if (t.empty() || static_cast<double>(n_good) < o.temperature_min_good_fraction * static_cast<double>(t.size())) return {};
  std::vector<double> out(t.size());
  const std::size_t first = static_cast<std::size_t>(std::find(good.begin(), good.end(), 1) - good.begin());
  double held = t[first];
  for (std::size_t i = 0; i < t.size(); ++i) {
    if (good[i]) held = t[i];
    else ++r.temperature_held;
    out[i] = held;
  }
  return out;
}

void check_options(const ControllerLogOptions& o, const std::string& path) {
  if (axis_index_or_none(o.axis) < 0) throw DataError(path + ": axis must be one of " + axis_names_list() + ", got '" + o.axis + "'");
  if (!std::isfinite(o.volts_per_step) || o.volts_per_step == 0.0)
    throw DataError(path + ": volts per step must be a finite value other than 0");
  if (!std::isfinite(o.nm_per_count) || o.nm_per_count == 0.0)
    throw DataError(path + ": nm per count must be a finite value other than 0");
}

// One row's reads: their mean (NaN without a finite read) and its contribution to the pooled spread.
struct RowReads {
  double mean = NAN, ss = 0;
  std::size_t n = 0;
};
RowReads row_reads(const std::vector<std::string_view>& cells, const LogColumns& c, const std::string& path,
                   std::size_t row, const std::string& axis, ControllerLogReport& r) {
  RowReads rr;
  double sum = 0;
  std::vector<double> v;
  for (std::size_t k = 0; k < c.reads.size(); ++k) {
    const double x = number(cells[static_cast<std::size_t>(c.reads[k])], true, path, row, axis + "_" + std::to_string(k));
    if (std::isfinite(x)) v.push_back(x), sum += x;
    else ++r.read_cells_bad;
  }
  rr.n = v.size();
  if (v.empty()) return rr;
  rr.mean = sum / static_cast<double>(v.size());
  for (double x : v) rr.ss += (x - rr.mean) * (x - rr.mean);
  return rr;
}

}  // namespace

Dataset import_controller_log(const std::string& path, const ControllerLogOptions& o, ControllerLogReport* report_out) {
  check_options(o, path);
  std::ifstream in(path, std::ios::binary);
  if (!in) throw DataError(path + ": cannot open file");
  ControllerLogReport r;
  std::string line;
  if (!std::getline(in, line) || line.empty()) throw DataError(path + ": file is empty (expected a header row)");
  const LogColumns c = map_columns(split_cells(line), path, o.axis);
  r.reads_per_row = c.reads.size();
  r.has_temperature = c.temperature >= 0;

  Dataset d;
  d.source = path;
  AxisSeries& ax = d.add_axis(o.axis);
  std::vector<double> temperature, setpoint_steps;
  double ss = 0, dof = 0, all_ss = 0, all_dof = 0, hold_ss = 0;
  std::size_t row = 1;
  while (std::getline(in, line)) {
    ++row;
    if (line.empty() || line == "\r") continue;
    const auto cells = split_cells(line);
    if (cells.size() != c.width)
      throw DataError(path + ": row " + std::to_string(row) + ": " + std::to_string(cells.size()) + " cells, the header has " +
                      std::to_string(c.width));
    ++r.rows_in;
    const double step = number(cells[static_cast<std::size_t>(c.setpoint)], false, path, row, "finestep");
    const double t = number(cells[static_cast<std::size_t>(c.time)], false, path, row, "time");
    const RowReads rr = row_reads(cells, c, path, row, o.axis, r);
    if (c.mean >= 0 && std::isfinite(rr.mean) && rr.n == c.reads.size()) {
      const double logged = number(cells[static_cast<std::size_t>(c.mean)], true, path, row, o.axis + "_mean");
      if (std::isfinite(logged) && std::fabs(logged - rr.mean) > 1e-6 * std::max(1.0, std::fabs(rr.mean)) + 1e-9)
        throw DataError(path + ": row " + std::to_string(row) + ", column " + o.axis + "_mean: " + std::string(cells[static_cast<std::size_t>(c.mean)]) +
                        " is not the mean of the reads (" + std::to_string(rr.mean) + ")");
      r.mean_column_checked = true;
    }
    if (!d.time_s.empty() && !(t > d.time_s.back()))
      throw DataError(path + ": row " + std::to_string(row) + ", column time: time does not increase (" +
                      std::to_string(d.time_s.back()) + " then " + std::string(cells[static_cast<std::size_t>(c.time)]) + ")");
    if (!std::isfinite(rr.mean)) {
      ++r.rows_without_reading;
      continue;
    }
    all_ss += rr.ss, all_dof += static_cast<double>(rr.n) - 1.0;
    if (!setpoint_steps.empty() && setpoint_steps.back() == step) {
      ss += rr.ss, dof += static_cast<double>(rr.n) - 1.0;  // the tip moves little while the set point holds
      const double diff = rr.mean - ax.position_nm.back() / o.nm_per_count;
      hold_ss += diff * diff, ++r.hold_pairs;
    }
    d.time_s.push_back(t);
    setpoint_steps.push_back(step);
    ax.voltage_v.push_back(step * o.volts_per_step);
    ax.position_nm.push_back(rr.mean * o.nm_per_count);
    if (c.temperature >= 0) temperature.push_back(number(cells[static_cast<std::size_t>(c.temperature)], true, path, row, "temp"));
  }
  if (d.time_s.empty()) throw DataError(path + ": no row with a reading after the header");
  r.rows_out = d.size();
  const double q = std::fabs(o.nm_per_count);
  if (r.hold_pairs < 100) ss = all_ss, dof = all_dof;  // too few held set points: every row's spread, motion included
  r.read_sigma_nm = dof > 0 ? q * std::sqrt(ss / dof) : 0.0;
  r.mean_sigma_independent_nm = r.read_sigma_nm / std::sqrt(static_cast<double>(c.reads.size()));
  r.mean_sigma_holds_nm = r.hold_pairs ? q * std::sqrt(hold_ss / static_cast<double>(r.hold_pairs) / 2.0) : 0.0;
  const auto [lo, hi] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
  r.voltage_min_v = *lo, r.voltage_max_v = *hi;
  if (c.temperature >= 0) {
    std::vector<double> fixed = repair_temperature(temperature, o, r);
    r.temperature_kept = !fixed.empty();
    if (r.temperature_kept) d.aux.push_back({"temperature_c", std::move(fixed)});
  }
  d.validate();
  if (report_out) *report_out = r;
  return d;
}

}  // namespace piezo::io
