#include "piezo_compensation/io/dataset.h"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace piezo::io {

std::string voltage_column(const std::string& axis) { return axis + "_voltage_v"; }
std::string voltage_column_axis(const std::string& column) {
  static const std::string suffix = "_voltage_v";
  if (column.size() <= suffix.size() || column.compare(column.size() - suffix.size(), suffix.size(), suffix) != 0) return {};
  return column.substr(0, column.size() - suffix.size());
}
bool is_voltage_column(const std::string& column) { return !voltage_column_axis(column).empty(); }
std::string position_column(const std::string& axis) { return axis + "_position_nm"; }
std::string true_position_column(const std::string& axis) { return axis + "_true_position_nm"; }
std::string fused_position_column(const std::string& axis) { return axis + "_fused_position_nm"; }

namespace {
std::string where(const Dataset& d) { return d.source.empty() ? std::string("data set") : d.source; }
}  // namespace

bool Dataset::has_axis(const std::string& name) const {
  return std::any_of(axes.begin(), axes.end(), [&](const AxisSeries& a) { return a.name == name; });
}

const AxisSeries& Dataset::axis(const std::string& name) const {
  for (const auto& a : axes)
    if (a.name == name) return a;
  throw DataError(where(*this) + ": missing column " + voltage_column(name) + " / " + position_column(name) +
                  " (axis '" + name + "' not in the data)");
}

AxisSeries& Dataset::axis(const std::string& name) {
  return const_cast<AxisSeries&>(static_cast<const Dataset&>(*this).axis(name));
}

AxisSeries& Dataset::add_axis(const std::string& name) {
  for (auto& a : axes)
    if (a.name == name) return a;
  AxisSeries s;
  s.name = name;
  s.voltage_v.assign(size(), 0.0);
  s.position_nm.assign(size(), 0.0);
  axes.push_back(std::move(s));
  // keep a, b, c order so files are written in a predictable column order
  std::stable_sort(axes.begin(), axes.end(), [](const AxisSeries& x, const AxisSeries& y) { return x.name < y.name; });
  for (auto& a : axes)
    if (a.name == name) return a;
  return axes.back();  // unreachable
}

const AuxSignal* Dataset::find_aux(const std::string& name) const {
  for (const auto& s : aux)
    if (s.name == name) return &s;
  return nullptr;
}

double Dataset::sample_period_s() const {
  if (time_s.size() < 2) throw DataError(where(*this) + ": need at least 2 samples to know the sample rate");
  for (std::size_t i = 1; i < time_s.size(); ++i)
    if (!(time_s[i] > time_s[i - 1])) {
      std::ostringstream os;
      os << where(*this) << ": row " << i + 2 << ", column time_s: time does not increase (" << time_s[i - 1] << " then "
         << time_s[i] << ")";
      throw DataError(os.str());
    }
  const TimeBase tb = time_base(time_s);
  if (tb.longest_step_s > kMaxStepS) {
    std::ostringstream os;
    os << where(*this) << ": row " << tb.longest_row + 2 << ", column time_s: a gap of " << tb.longest_step_s
       << " s after t = " << time_s[tb.longest_row - 1] << " s (usual step " << tb.period_s << " s); a model steps over at most "
       << kMaxStepS << " s as one sample: split the recording there";
    throw DataError(os.str());
  }
  return tb.period_s;
}

TimeBase time_base(const std::vector<double>& time_s) {
  TimeBase tb;
  tb.rows = time_s.size();
  if (tb.rows < 2) return tb;
  tb.period_s = median_step_s(time_s);
  tb.mean_step_s = (time_s.back() - time_s.front()) / static_cast<double>(tb.rows - 1);
  double ss = 0;
  std::size_t on_time = 0;
  for (std::size_t i = 1; i < tb.rows; ++i) {
    const double step = time_s[i] - time_s[i - 1], dev = step - tb.period_s;
    if (std::fabs(dev) > 0.01 * std::fabs(tb.period_s) + 1e-9) tb.constant = false;
    if (step > tb.longest_step_s) tb.longest_step_s = step, tb.longest_row = i;
    if (step > kLateStepFactor * tb.period_s) {
      ++tb.late_steps;
      tb.late_s += dev;
    } else {
      ss += dev * dev;
      ++on_time;
    }
  }
  tb.jitter_s = on_time ? std::sqrt(ss / static_cast<double>(on_time)) : 0.0;
  // On a sample clock the mean step is the precise one (a stamp's rounding moves a single step, not the span).
  if (tb.constant) tb.period_s = tb.mean_step_s;
  tb.clock_lag_s = (time_s.back() - time_s.front()) - static_cast<double>(tb.rows - 1) * tb.period_s;
  return tb;
}

double median_step_s(const std::vector<double>& time_s) {
  if (time_s.size() < 2) return 0.0;
  std::vector<double> steps(time_s.size() - 1);
  for (std::size_t j = 1; j < time_s.size(); ++j) steps[j - 1] = time_s[j] - time_s[j - 1];
  std::nth_element(steps.begin(), steps.begin() + static_cast<long>(steps.size() / 2), steps.end());
  return steps[steps.size() / 2];
}

Dataset Dataset::slice(std::size_t begin, std::size_t end) const {
  end = std::min(end, size());
  begin = std::min(begin, end);
  auto cut = [&](const std::vector<double>& v) {
    return v.empty() ? v : std::vector<double>(v.begin() + begin, v.begin() + end);
  };
  Dataset out;
  out.source = source;
  out.time_clock = time_clock;
  out.origin = origin;
  out.time_s = cut(time_s);
  for (const auto& a : axes) {
    AxisSeries s;
    s.name = a.name;
    s.voltage_v = cut(a.voltage_v);
    s.position_nm = cut(a.position_nm);
    s.true_position_nm = cut(a.true_position_nm);
    out.axes.push_back(std::move(s));
  }
  for (const auto& x : aux) out.aux.push_back({x.name, cut(x.values)});
  if (!segment.empty()) out.segment.assign(segment.begin() + begin, segment.begin() + end);
  if (!phase.empty()) out.phase.assign(phase.begin() + begin, phase.begin() + end);
  for (std::size_t k = 0; k < recordings.size(); ++k) {
    const auto [b, e] = recording_rows(k);
    if (e <= begin || b >= end) continue;
    RecordingMark m = recordings[k];
    m.begin = std::max(b, begin) - begin;
    out.recordings.push_back(m);
  }
  return out;
}

std::pair<std::size_t, std::size_t> Dataset::recording_rows(std::size_t k) const {
  if (recordings.empty()) return {0, size()};
  return {recordings.at(k).begin, k + 1 < recordings.size() ? recordings[k + 1].begin : size()};
}

bool Dataset::starts_recording(std::size_t row) const {
  if (row == 0) return true;
  for (const auto& m : recordings)
    if (m.begin == row) return true;
  return false;
}

std::vector<std::size_t> Dataset::recording_index() const {
  std::vector<std::size_t> idx(size(), 0);
  for (std::size_t k = 0; k < recordings.size(); ++k) {
    const auto [b, e] = recording_rows(k);
    std::fill(idx.begin() + static_cast<long>(b), idx.begin() + static_cast<long>(e), k);
  }
  return idx;
}

Dataset Dataset::recording(std::size_t k) const {
  if (k >= recording_count()) throw DataError(where(*this) + ": no recording " + std::to_string(k));
  const auto [b, e] = recording_rows(k);
  Dataset out = slice(b, e);
  if (!recordings.empty()) {
    out.source = recordings[k].name;
    for (double& t : out.time_s) t -= recordings[k].time_shift_s;
    out.recordings.clear();
  }
  return out;
}

bool is_simulated(const Dataset& data) {
  if (!data.origin.empty()) return data.origin == kOriginSimulated;
  return std::any_of(data.axes.begin(), data.axes.end(), [](const AxisSeries& a) { return a.has_truth(); });
}

Dataset join_recordings(const std::vector<Dataset>& parts, std::vector<std::string>* notes) {
  if (parts.empty()) throw DataError("no data to join");
  if (parts.size() == 1) return parts[0];
  auto note = [&](const std::string& n) {
    if (notes) notes->push_back(n);
  };
  const Dataset& first = parts[0];
  for (const auto& p : parts) {
    if (p.empty()) throw DataError(p.source_or_data() + ": no rows");
    if (p.recording_count() != 1) throw DataError(p.source_or_data() + ": already holds several recordings");
    for (const auto& a : first.axes)
      if (!p.has_axis(a.name))
        throw DataError(p.source_or_data() + ": has no axis " + a.name + " (" + first.source_or_data() + " has)");
    for (const auto& a : p.axes)
      if (!first.has_axis(a.name))
        throw DataError(p.source_or_data() + ": has axis " + a.name + ", which " + first.source_or_data() + " has not");
  }
  auto in_all = [&](auto has) { return std::all_of(parts.begin(), parts.end(), has); };
  Dataset out;
  out.source = first.source_or_data() + " and " + std::to_string(parts.size() - 1) + " more";
  out.time_clock = first.time_clock;
  // simulated when any part is (its truth may be left out below), recorded when every part says so
  if (std::any_of(parts.begin(), parts.end(), [](const Dataset& p) { return is_simulated(p); }))
    out.origin = kOriginSimulated;
  else if (in_all([](const Dataset& p) { return p.origin == kOriginRecorded; }))
    out.origin = kOriginRecorded;
  std::vector<std::string> aux_names;
  for (const auto& x : first.aux) {
    if (in_all([&](const Dataset& p) { return p.find_aux(x.name) != nullptr; })) aux_names.push_back(x.name);
    else note("aux column " + x.name + " left out: not every recording has it");
  }
  for (const auto& p : parts)
    for (const auto& x : p.aux)
      if (!first.find_aux(x.name)) note("aux column " + x.name + " of " + p.source_or_data() + " left out: not every recording has it");
  const bool segments = in_all([](const Dataset& p) { return !p.segment.empty(); });
  const bool phases = in_all([](const Dataset& p) { return !p.phase.empty(); });
  if (!segments && !first.segment.empty()) note("segment markers left out: not every recording has them");
  if (!phases && !first.phase.empty()) note("phase markers left out: not every recording has them");
  for (const auto& a : first.axes) {
    AxisSeries& s = out.add_axis(a.name);
    s.voltage_v.clear(), s.position_nm.clear();
  }
  for (auto& s : out.axes) {
    const bool truth = in_all([&](const Dataset& p) { return p.axis(s.name).has_truth(); });
    if (!truth && first.axis(s.name).has_truth()) note("true position of axis " + s.name + " left out: not every recording has it");
    for (const auto& p : parts) {
      const AxisSeries& a = p.axis(s.name);
      s.voltage_v.insert(s.voltage_v.end(), a.voltage_v.begin(), a.voltage_v.end());
      s.position_nm.insert(s.position_nm.end(), a.position_nm.begin(), a.position_nm.end());
      if (truth) s.true_position_nm.insert(s.true_position_nm.end(), a.true_position_nm.begin(), a.true_position_nm.end());
    }
  }
  for (const auto& name : aux_names) {
    AuxSignal x{name, {}};
    for (const auto& p : parts) x.values.insert(x.values.end(), p.find_aux(name)->values.begin(), p.find_aux(name)->values.end());
    out.aux.push_back(std::move(x));
  }
  for (const auto& p : parts) {
    RecordingMark m;
    m.name = p.source_or_data();
    m.begin = out.size();
    const double period = p.size() > 1 ? median_step_s(p.time_s) : (out.empty() ? 1.0 : median_step_s(out.time_s));
    m.time_shift_s = out.empty() ? 0.0 : out.time_s.back() + period - p.time_s.front();
    for (double t : p.time_s) out.time_s.push_back(t + m.time_shift_s);
    if (segments) out.segment.insert(out.segment.end(), p.segment.begin(), p.segment.end());
    if (phases) out.phase.insert(out.phase.end(), p.phase.begin(), p.phase.end());
    out.recordings.push_back(m);
  }
  return out;
}

void Dataset::append(const Dataset& other) {
  if (other.empty()) return;
  if (other.recording_count() > 1)
    throw DataError(where(other) + ": cannot append several recordings as one (io::join_recordings keeps them apart)");
  if (empty() && axes.empty()) {
    const std::string src = source;
    *this = other;
    if (!src.empty()) source = src;
    return;
  }
  if (!time_s.empty() && !(other.time_s.front() > time_s.back()))
    throw DataError(where(other) + ": column time_s: appended data does not continue after t=" +
                    std::to_string(time_s.back()) + " s");
  if (other.axes.size() != axes.size() || other.aux.size() != aux.size())
    throw DataError(where(other) + ": cannot append: different columns");
  for (std::size_t k = 0; k < axes.size(); ++k) {
    if (other.axes[k].name != axes[k].name || other.axes[k].has_truth() != axes[k].has_truth())
      throw DataError(where(other) + ": cannot append: different axis columns");
    auto& a = axes[k];
    const auto& b = other.axes[k];
    a.voltage_v.insert(a.voltage_v.end(), b.voltage_v.begin(), b.voltage_v.end());
    a.position_nm.insert(a.position_nm.end(), b.position_nm.begin(), b.position_nm.end());
    a.true_position_nm.insert(a.true_position_nm.end(), b.true_position_nm.begin(), b.true_position_nm.end());
  }
  for (std::size_t k = 0; k < aux.size(); ++k) {
    if (other.aux[k].name != aux[k].name) throw DataError(where(other) + ": cannot append: different aux columns");
    aux[k].values.insert(aux[k].values.end(), other.aux[k].values.begin(), other.aux[k].values.end());
  }
  if (segment.empty() != other.segment.empty() || phase.empty() != other.phase.empty())
    throw DataError(where(other) + ": cannot append: segment/phase columns differ");
  segment.insert(segment.end(), other.segment.begin(), other.segment.end());
  phase.insert(phase.end(), other.phase.begin(), other.phase.end());
  time_s.insert(time_s.end(), other.time_s.begin(), other.time_s.end());
  if (is_simulated(other) && !is_simulated(*this)) origin = kOriginSimulated;
}

void Dataset::validate() const {
  const std::size_t n = size();
  auto check = [&](const std::vector<double>& v, const std::string& col, bool optional) {
    if (optional && v.empty()) return;
    if (v.size() != n)
      throw DataError(where(*this) + ": column " + col + " has " + std::to_string(v.size()) + " values, time_s has " +
                      std::to_string(n));
    for (std::size_t i = 0; i < n; ++i)
      if (!std::isfinite(v[i]))
        throw DataError(where(*this) + ": row " + std::to_string(i + 2) + ", column " + col + ": not a finite number");
  };
  check(time_s, "time_s", false);
  for (std::size_t i = 1; i < n; ++i)
    if (!(time_s[i] > time_s[i - 1]))
      throw DataError(where(*this) + ": row " + std::to_string(i + 2) + ", column time_s: time does not increase (" +
                      std::to_string(time_s[i - 1]) + " then " + std::to_string(time_s[i]) + ")");
  if (axes.empty()) throw DataError(where(*this) + ": no axis columns (<axis>_voltage_v and <axis>_position_nm)");
  for (const auto& a : axes) {
    check(a.voltage_v, voltage_column(a.name), false);
    check(a.position_nm, position_column(a.name), false);
    check(a.true_position_nm, true_position_column(a.name), true);
  }
  for (const auto& x : aux) check(x.values, x.name, false);
  if (!segment.empty() && segment.size() != n) throw DataError(where(*this) + ": column segment has the wrong length");
  if (!phase.empty() && phase.size() != n) throw DataError(where(*this) + ": column phase has the wrong length");
  for (std::size_t k = 0; k < recordings.size(); ++k)
    if ((k == 0 && recordings[k].begin != 0) || (k > 0 && !(recordings[k].begin > recordings[k - 1].begin)) ||
        recordings[k].begin >= std::max<std::size_t>(n, 1))
      throw DataError(where(*this) + ": recording " + std::to_string(k) + " (" + recordings[k].name +
                      ") does not start after the one before");
}

DataSpan data_span(const Dataset& data, const std::string& axis) {
  const auto& v = data.axis(axis).voltage_v;
  DataSpan s;
  s.sample_rate_hz = data.sample_rate_hz();
  s.duration_s = static_cast<double>(data.size()) / s.sample_rate_hz;
  bool any = false;
  for (double x : v)
    if (std::isfinite(x)) {
      s.voltage_min_v = any ? std::min(s.voltage_min_v, x) : x;
      s.voltage_max_v = any ? std::max(s.voltage_max_v, x) : x;
      any = true;
    }
  return s;
}

}  // namespace piezo::io
