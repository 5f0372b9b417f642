#include "piezo_compensation/compensation/snapshot_buffer.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <type_traits>

namespace piezo::compensation {

namespace {

// Puts one axis' samples on the sample clock (Snapshot): readings by sequence distance from the newest, reports
// onto the stamp of their reading (or shifted like the reading before them when theirs was lost). Records the gaps.
void restamp(const std::string& axis, Snapshot::Axis& a, Snapshot& s) {
  auto& r = a.readings;
  if (r.empty()) return;
  const std::size_t n = r.size();
  const double rough = n > 1 ? (r.back().received_s - r.front().received_s) / static_cast<double>(n - 1) : 0.0;
  std::vector<double> index(n, 0.0);  // sample number from the first reading
  for (std::size_t i = 1; i < n; ++i) {
    const std::uint32_t dseq = r[i].sequence - r[i - 1].sequence;  // wraps at 2^32 like the counter
    double step = static_cast<double>(dseq);
    if (dseq == 0 || dseq > 1000)  // a controller restart: count the periods by time
      step = rough > 0.0 ? std::max(1.0, std::round((r[i].received_s - r[i - 1].received_s) / rough)) : 1.0;
    index[i] = index[i - 1] + step;
  }
  const double period = index.back() > 0.0 ? (r.back().received_s - r.front().received_s) / index.back() : 0.0;
  if (s.period_s == 0.0) s.period_s = period;
  std::map<std::uint32_t, double> shift;  // sequence → sample clock − receive stamp
  for (std::size_t i = 0; i < n; ++i) {
    const double clock = r.back().received_s - (index.back() - index[i]) * period;
    s.max_restamp_s = std::max(s.max_restamp_s, std::fabs(clock - r[i].received_s));
    shift[r[i].sequence] = clock - r[i].received_s;
    r[i].stamp_s = clock;
  }
  for (std::size_t i = 1; i < n; ++i)
    if (index[i] - index[i - 1] > 1.0)
      s.gaps.push_back({axis, r[i - 1].stamp_s, r[i].stamp_s, static_cast<std::size_t>(index[i] - index[i - 1] - 1.0)});
  double last = 0.0;
  for (auto& v : a.voltages) {
    const auto it = shift.find(v.sequence);
    if (it != shift.end()) last = it->second;
    v.stamp_s = v.received_s + last;
  }
}

// A voltage report and its reading carry stamps of the same sample; a controller restart reuses numbers only
// much later, so a match within this is the report of that reading.
constexpr double kSameSampleS = 1.0;
}  // namespace

SnapshotBuffer::SnapshotBuffer(const SnapshotOptions& o) : o_(o) {
  if (!(o_.duration_s > 0.0) || !std::isfinite(o_.duration_s))
    throw std::invalid_argument("snapshot duration_s must be finite and > 0");
  if (o_.max_messages < 2) throw std::invalid_argument("snapshot max_messages must be at least 2");
  if (!(o_.expected_rate_hz > 0.0) || !(o_.expected_rate_hz <= 100000.0))
    throw std::invalid_argument("snapshot expected_rate_hz must be > 0 and <= 100000");
  if (!(o_.min_fraction > 0.0) || !(o_.min_fraction <= o_.prefer_recent_fraction) || !(o_.prefer_recent_fraction <= 1.0))
    throw std::invalid_argument("snapshot fractions must satisfy 0 < min_fraction <= prefer_recent_fraction <= 1");
  // What push() keeps at the expected rate (duration_s plus its 1 s headroom), 5 % more for a controller clock
  // running fast and receive jitter, and the one aux value before the window.
  const double need = std::ceil((o_.duration_s + kSameSampleS) * o_.expected_rate_hz * 1.05) + 2.0;
  initial_capacity_ = need >= static_cast<double>(o_.max_messages) ? o_.max_messages : static_cast<std::size_t>(need);
  for (const auto& axis : o_.axes) axis_streams(axis);
  for (const auto& name : o_.aux) aux_stream(name);
}

SnapshotBuffer::AxisStreams& SnapshotBuffer::axis_streams(const std::string& axis) {
  auto it = axes_.find(axis);
  if (it == axes_.end()) {  // allocates: an axis not named in the options, once, on its first message
    AxisStreams a{SnapshotRing<SnapshotVoltage>(initial_capacity_), SnapshotRing<Reading>(initial_capacity_),
                  SnapshotRing<SnapshotPrediction>(initial_capacity_)};
    it = axes_.emplace(axis, std::move(a)).first;
  }
  return it->second;
}

SnapshotRing<SnapshotAux>& SnapshotBuffer::aux_stream(const std::string& name) {
  auto it = aux_.find(name);
  if (it == aux_.end()) it = aux_.emplace(name, SnapshotRing<SnapshotAux>(initial_capacity_)).first;
  return it->second;
}

template <class T>
void SnapshotBuffer::push(SnapshotRing<T>& q, const T& e, bool keep_one_before) {
  // Some headroom beyond duration_s, so take() still finds the report of the first reading it keeps.
  const auto stamp = [](const auto& x) {
    if constexpr (std::is_same_v<std::decay_t<decltype(x)>, Reading>) return x.r.stamp_s;
    else return x.stamp_s;
  };
  const double cut = stamp(e) - o_.duration_s - kSameSampleS;
  while (!q.empty() && stamp(q.front()) < cut && (!keep_one_before || (q.size() > 1 && stamp(q[1]) < cut)))
    q.pop_front();
  if (q.size() == q.capacity()) {
    if (q.capacity() < o_.max_messages) {
      // A stream faster than expected_rate_hz (or a burst) outgrows its ring: double it, up to max_messages. This
      // allocates in the callback, and is counted (grown()).
      q.grow(std::min(o_.max_messages, std::max<std::size_t>(2 * q.capacity(), 2)));
      ++grown_;
    } else {
      q.pop_front();  // the memory bound: the oldest goes
    }
  }
  q.push_back(e);
}

void SnapshotBuffer::add_voltage(const std::string& axis, std::uint32_t sequence, double voltage_v, double stamp_s) {
  if (!std::isfinite(voltage_v) || !std::isfinite(stamp_s)) return;
  push(axis_streams(axis).voltages, SnapshotVoltage{stamp_s, stamp_s, sequence, voltage_v}, false);
}

void SnapshotBuffer::add_reading(const std::string& axis, std::uint32_t sequence, double position_nm, bool valid,
                                 double stamp_s) {
  if (!std::isfinite(stamp_s)) return;
  if (!std::isfinite(position_nm)) valid = false;
  push(axis_streams(axis).readings, Reading{{stamp_s, stamp_s, sequence, valid ? position_nm : 0.0}, valid}, false);
}

void SnapshotBuffer::add_prediction(const std::string& axis, std::uint32_t sequence, double base_nm, double stamp_s) {
  if (!std::isfinite(base_nm) || !std::isfinite(stamp_s)) return;
  push(axis_streams(axis).predictions, SnapshotPrediction{stamp_s, sequence, base_nm}, false);
}

void SnapshotBuffer::add_aux(const std::string& name, double value, double stamp_s) {
  if (!std::isfinite(value) || !std::isfinite(stamp_s)) return;
  push(aux_stream(name), SnapshotAux{stamp_s, value}, true);  // the value in force at the window's start
}

std::size_t SnapshotBuffer::messages() const {
  std::size_t n = 0;
  for (const auto& [name, a] : axes_) n += a.voltages.size() + a.readings.size() + a.predictions.size();
  for (const auto& [name, q] : aux_) n += q.size();
  return n;
}

std::size_t SnapshotBuffer::capacity() const {
  std::size_t n = 0;
  for (const auto& [name, a] : axes_) n += a.voltages.capacity() + a.readings.capacity() + a.predictions.capacity();
  for (const auto& [name, q] : aux_) n += q.capacity();
  return n;
}

Snapshot SnapshotBuffer::take() const {
  double end = -std::numeric_limits<double>::infinity();
  for (const auto& [name, a] : axes_)
    if (!a.readings.empty()) end = std::max(end, a.readings.back().r.stamp_s);
  if (!std::isfinite(end)) throw std::runtime_error("nothing recorded yet (no encoder reading)");

  // index of the voltage report of reading r, or npos
  const auto report_of = [](const AxisStreams& a, const SnapshotReading& r) {
    for (std::size_t i = 0; i < a.voltages.size(); ++i)
      if (a.voltages[i].sequence == r.sequence && std::fabs(a.voltages[i].stamp_s - r.stamp_s) <= kSameSampleS)
        return i;
    return a.voltages.size();
  };
  // first valid reading at or after t whose report is held: (reading index, report index)
  const auto first_complete = [&](const AxisStreams& a, double t) {
    for (std::size_t i = 0; i < a.readings.size(); ++i) {
      const Reading& r = a.readings[i];
      if (r.r.stamp_s < t || !r.valid) continue;
      const std::size_t v = report_of(a, r.r);
      if (v < a.voltages.size()) return std::make_pair(i, v);
    }
    return std::make_pair(a.readings.size(), a.voltages.size());
  };

  // Every axis and every aux signal must be present from the first row on: the start is the latest of their
  // first complete samples.
  double start = end - o_.duration_s;
  for (const auto& [name, a] : axes_) {
    const auto [ri, vi] = first_complete(a, start);
    if (ri == a.readings.size())
      throw std::runtime_error("axis " + name + ": no encoder reading with its voltage report in the last " +
                               std::to_string(o_.duration_s) + " s");
    start = std::max(start, a.readings[ri].r.stamp_s);
  }
  for (const auto& [name, q] : aux_)
    if (!q.empty() && q.front().stamp_s > start) start = q.front().stamp_s;

  Snapshot s;
  s.begin_s = std::numeric_limits<double>::infinity();
  s.end_s = end;
  for (const auto& [name, a] : axes_) {
    const auto [ri, vi] = first_complete(a, start);
    if (ri == a.readings.size()) {
      std::ostringstream os;
      os << "axis " << name << ": no encoder reading with its voltage report after t = " << std::fixed << start
         << " s (an aux signal or another axis starts later)";
      throw std::runtime_error(os.str());
    }
    Snapshot::Axis& out = s.axes[name];
    for (std::size_t i = vi; i < a.voltages.size(); ++i) out.voltages.push_back(a.voltages[i]);
    for (std::size_t i = ri; i < a.readings.size(); ++i) {
      if (a.readings[i].valid) out.readings.push_back(a.readings[i].r);
      else ++s.invalid_readings;
    }
    const double first_s = a.readings[ri].r.stamp_s - kSameSampleS;
    for (std::size_t i = 0; i < a.predictions.size(); ++i)
      if (a.predictions[i].stamp_s >= first_s) out.base_predictions.push_back(a.predictions[i]);
  }
  for (auto& [name, a] : s.axes) {
    restamp(name, a, s);
    s.begin_s = std::min(s.begin_s, a.readings.front().stamp_s);
  }
  std::sort(s.gaps.begin(), s.gaps.end(), [](const SnapshotGap& x, const SnapshotGap& y) { return x.after_s < y.after_s; });
  for (const auto& [name, q] : aux_) {
    if (q.empty()) continue;
    std::size_t k = 0;
    while (k + 1 < q.size() && q[k + 1].stamp_s <= s.begin_s) ++k;  // the value in force at the first row
    auto& out = s.aux[name];
    for (std::size_t i = k; i < q.size(); ++i) out.push_back(q[i]);
  }
  return s;
}

std::string describe_gaps(const Snapshot& s) {
  std::size_t missing = 0;
  for (const auto& g : s.gaps) missing += g.missing;
  std::ostringstream os;
  os << std::fixed << std::setprecision(1) << s.gaps.size() << (s.gaps.size() == 1 ? " gap" : " gaps") << ", "
     << missing << " samples missing (";
  const std::size_t shown = std::min<std::size_t>(s.gaps.size(), 4);
  for (std::size_t i = 0; i < shown; ++i) {
    const SnapshotGap& g = s.gaps[i];
    os << (i ? "; " : "") << g.missing << " on " << g.axis << " after +" << g.after_s - s.begin_s << " s, t = "
       << std::setprecision(2) << g.after_s << std::setprecision(1) << " s";
  }
  if (shown < s.gaps.size()) os << "; " << s.gaps.size() - shown << " more";
  os << ")";
  return os.str();
}

namespace {
// The first row needs its report on every axis, and every axis a reading there (as take() cuts): readings and
// voltages before it are dropped until every axis starts on a reading whose voltage report is there.
void align_first_row(Snapshot& c, double tol, const Snapshot& s) {
  for (bool changed = true; changed;) {
    changed = false;
    double first = -std::numeric_limits<double>::infinity();
    for (const auto& [name, b] : c.axes) {
      if (b.readings.empty())
        throw std::runtime_error("axis " + name + ": no encoder reading with its voltage report in the stretch without "
                                 "a missing sample (" + describe_gaps(s) + ")");
      first = std::max(first, b.readings.front().stamp_s);
    }
    for (auto& [name, b] : c.axes) {
      auto& r = b.readings;
      auto& v = b.voltages;
      const auto r_keep = std::find_if(r.begin(), r.end(), [&](const SnapshotReading& x) { return x.stamp_s >= first - tol; });
      if (r_keep != r.begin()) r.erase(r.begin(), r_keep), changed = true;
      if (r.empty()) continue;
      const auto v_keep = std::find_if(v.begin(), v.end(), [&](const SnapshotVoltage& x) { return x.stamp_s >= r.front().stamp_s - tol; });
      v.erase(v.begin(), v_keep);
      if (v.empty() || v.front().sequence != r.front().sequence) r.erase(r.begin()), changed = true;
    }
  }
}

}  // namespace

SnapshotStretch gap_free_stretch(const Snapshot& s, double prefer_recent_fraction, double min_fraction) {
  SnapshotStretch out;
  if (s.gaps.empty()) {
    out.snapshot = s;
    return out;
  }
  // the stretches between the gaps of all axes (gaps of different axes may overlap)
  struct Span {
    double begin, end;
    double length() const { return end - begin; }
  };
  std::vector<Span> spans;
  double start = s.begin_s;
  for (const auto& g : s.gaps) {  // by after_s
    if (g.after_s >= start) spans.push_back({start, g.after_s});
    start = std::max(start, g.before_s);
  }
  spans.push_back({start, s.end_s});
  const double window = s.end_s - s.begin_s;
  const Span& recent = spans.back();
  const Span* longest = &spans.front();
  for (const auto& sp : spans)
    if (sp.length() >= longest->length()) longest = &sp;  // the later of equal ones
  const bool take_recent = recent.length() >= prefer_recent_fraction * window;
  const Span chosen = take_recent ? recent : *longest;
  std::ostringstream os;
  os << std::fixed << std::setprecision(1);
  if (!take_recent && chosen.length() < min_fraction * window) {
    os << "the " << window << " s window has no stretch without a missing sample of at least " << min_fraction * window
       << " s (" << min_fraction * 100.0 << " % of it): " << describe_gaps(s) << "; the longest runs "
       << longest->length() << " s from +" << longest->begin - s.begin_s << " s";
    throw std::runtime_error(os.str());
  }

  // Every sample of the stretch on every axis: readings (and their reports) within half a period of it, the
  // axes' sample clocks being ms apart.
  const double tol = 0.5 * s.period_s;
  Snapshot& c = out.snapshot;
  c.period_s = s.period_s;
  c.invalid_readings = s.invalid_readings;
  std::size_t before = 0, after = 0;
  const auto within = [&](double t) { return t >= chosen.begin - tol && t <= chosen.end + tol; };
  for (const auto& [name, a] : s.axes) {
    Snapshot::Axis& b = c.axes[name];
    for (const auto& r : a.readings)
      if (within(r.stamp_s)) b.readings.push_back(r);
    for (const auto& v : a.voltages)
      if (within(v.stamp_s)) b.voltages.push_back(v);
    before += a.readings.size();
  }
  align_first_row(c, tol, s);
  c.begin_s = std::numeric_limits<double>::infinity();
  c.end_s = -std::numeric_limits<double>::infinity();
  for (auto& [name, b] : c.axes) {
    c.begin_s = std::min(c.begin_s, b.readings.front().stamp_s);
    c.end_s = std::max(c.end_s, b.readings.back().stamp_s);
    after += b.readings.size();
    std::vector<std::uint32_t> seqs;
    for (const auto& r : b.readings) {
      c.max_restamp_s = std::max(c.max_restamp_s, std::fabs(r.stamp_s - r.received_s));
      seqs.push_back(r.sequence);
    }
    std::sort(seqs.begin(), seqs.end());
    for (const auto& p : s.axes.at(name).base_predictions)
      if (std::binary_search(seqs.begin(), seqs.end(), p.sequence)) b.base_predictions.push_back(p);
  }
  for (const auto& [name, q] : s.aux) {
    std::size_t k = 0;
    while (k + 1 < q.size() && q[k + 1].stamp_s <= c.begin_s) ++k;  // the value in force at the first row
    auto& o = c.aux[name];
    for (std::size_t i = k; i < q.size() && (i == k || q[i].stamp_s <= c.end_s + tol); ++i) o.push_back(q[i]);
  }
  out.dropped_readings = before - after;
  os << "the " << window << " s window has " << describe_gaps(s) << ": wrote the "
     << (take_recent ? "most recent" : "longest") << " stretch without one, " << c.end_s - c.begin_s << " s from +"
     << c.begin_s - s.begin_s << " s";
  if (!take_recent)
    os << " (the most recent runs " << recent.length() << " s, under " << prefer_recent_fraction * 100.0 << " % of the window)";
  os << "; " << out.dropped_readings << " readings left out";
  out.message = os.str();
  return out;
}

}  // namespace piezo::compensation
