#include "piezo_compensation/io/message_rows.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/sequence_pairer.h"

namespace piezo::io {

namespace {

std::string axis_topic(const std::string& ns, const std::string& rest) {
  if (ns.empty() || ns == "/") return "/" + rest;
  return (ns.front() == '/' ? ns : "/" + ns) + (ns.back() == '/' ? "" : "/") + rest;
}

void sort_by_stamp(std::vector<StampedValue>& v) {
  std::stable_sort(v.begin(), v.end(), [](const StampedValue& a, const StampedValue& b) { return a.stamp_s < b.stamp_s; });
}

// The latest value at or before t; with nothing before t, the first one if it comes within one sample period.
const StampedValue* latest_at(const std::vector<StampedValue>& v, double t, double period_s) {
  auto it = std::upper_bound(v.begin(), v.end(), t + 1e-9, [](double x, const StampedValue& s) { return x < s.stamp_s; });
  if (it != v.begin()) return &*(it - 1);
  if (!v.empty() && v.front().stamp_s - t <= period_s) return &v.front();
  return nullptr;
}

// One axis' paired samples (in sequence order), indexed by sequence for the join across axes.
struct PairedAxis {
  std::vector<PairedSample> samples;
  std::vector<std::pair<std::uint32_t, std::uint32_t>> by_seq;  // (sequence, index), sorted
  std::uint64_t dropped = 0;
  // The sample with this sequence number within one period of t (a restart or a wrap reuses numbers), or null.
  // Never a neighbour: a sample this axis lost has no value to give.
  const PairedSample* match(std::uint32_t seq, double t, double period_s) const {
    auto it = std::lower_bound(by_seq.begin(), by_seq.end(), seq,
                               [](const auto& e, std::uint32_t s) { return e.first < s; });
    for (; it != by_seq.end() && it->first == seq; ++it)
      if (std::fabs(samples[it->second].stamp_s - t) <= period_s) return &samples[it->second];
    return nullptr;
  }
};

PairedAxis pair_axis_messages(const AxisMessages& m) {
  const bool with_truth = !m.truth.empty();
  PairerOptions o;
  o.with_truth = with_truth;
  SequencePairer pairer(o);
  PairedAxis out;
  out.samples.reserve(m.encoder.size());
  const auto take = [&](std::vector<PairedSample>&& ps) {
    for (auto& p : ps) out.samples.push_back(p);
  };
  // merge the three streams by stamp; on equal stamps the reports go before the reading
  std::size_t iv = 0, ie = 0, it = 0;
  const double inf = std::numeric_limits<double>::infinity();
  while (ie < m.encoder.size() || iv < m.voltage.size() || (with_truth && it < m.truth.size())) {
    const double tv = iv < m.voltage.size() ? m.voltage[iv].stamp_s : inf;
    const double tt = with_truth && it < m.truth.size() ? m.truth[it].stamp_s : inf;
    const double te = ie < m.encoder.size() ? m.encoder[ie].stamp_s : inf;
    if (tv <= tt && tv <= te) {
      const StampedValue& s = m.voltage[iv++];
      take(pairer.add_voltage(s.sequence, s.value, s.stamp_s));
    } else if (tt <= te) {
      const StampedValue& s = m.truth[it++];
      take(pairer.add_truth(s.sequence, s.value, s.stamp_s));
    } else {
      const StampedValue& s = m.encoder[ie++];
      take(pairer.add_reading(s.sequence, s.value, s.valid, s.stamp_s));
    }
  }
  take(pairer.flush());
  out.dropped = pairer.counters().dropped_samples;
  out.by_seq.resize(out.samples.size());
  for (std::size_t i = 0; i < out.samples.size(); ++i)
    out.by_seq[i] = {out.samples[i].sequence, static_cast<std::uint32_t>(i)};
  std::stable_sort(out.by_seq.begin(), out.by_seq.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  return out;
}

std::string at_row_col(const std::string& source, std::size_t row, const std::string& col) {
  std::ostringstream os;
  os << source << ": row " << row + 2 << ", column " << col << ": ";
  return os.str();
}

// What the messages hold per axis (before the streams are consumed by the pairing).
struct AxisPresence {
  bool voltage[3] = {}, encoder[3] = {}, truth[3] = {};
  bool has_axis(int k) const { return encoder[k]; }
};

// Every axis with messages has both voltage and encoder messages; returns the first such axis.
int first_recorded_axis(const AxisPresence& p, const RecordedMessages& m) {
  int first = -1;
  for (int k = 0; k < 3; ++k) {
    const std::string ax = kAxisNames[k];
    if (p.encoder[k] != p.voltage[k])
      throw DataError(m.source + ": axis " + ax + " has " + (p.encoder[k] ? "encoder" : "voltage") + " messages but no " +
                      axis_topic(m.ns, ax + (p.encoder[k] ? "/voltage" : "/encoder")));
    if (p.encoder[k] && first < 0) first = k;
  }
  if (first < 0) throw DataError(m.source + ": no encoder messages under namespace '" + m.ns + "'");
  return first;
}

// The rows of the data set: samples of the first axis joined with every other axis' sample of the same sequence.
struct JoinedRows {
  PairedAxis paired[3];
  int first = 0;
  std::vector<std::uint32_t> candidates;  // the first axis' samples with a reading
  std::vector<std::uint32_t> row_of;      // row → sample of the first axis
  double period = 1.0;
  const PairedSample* partner(int k, std::uint32_t i) const {
    const PairedSample& row = paired[first].samples[i];
    return k == first ? &row : paired[k].match(row.sequence, row.stamp_s, period);
  }
  double t(std::size_t r) const { return paired[first].samples[row_of[r]].stamp_s; }
};

// rows: the first axis' samples that have a reading (lost readings have no row) and whose sample every other
// axis has. A sample another axis lost is not filled from a neighbour: its row is left out, so the time column
// shows the gap as when the first axis lost it, which the offline tools step over as one sample (TimeBase);
// at the ends (one axis started or stopped a sample later) that cuts the rows without a partner.
void join_axis_rows(const AxisPresence& p, const std::string& source, JoinedRows& rows) {
  const int first = rows.first;
  const auto& samples = rows.paired[first].samples;
  for (std::uint32_t i = 0; i < samples.size(); ++i)
    if (!samples[i].reading_lost) rows.candidates.push_back(i);
  const auto& cand = rows.candidates;
  if (cand.size() >= 2)
    rows.period = (samples[cand.back()].stamp_s - samples[cand.front()].stamp_s) / static_cast<double>(cand.size() - 1);
  if (!(rows.period > 0.0)) rows.period = 1.0;
  std::size_t matched[3] = {};
  for (std::uint32_t i : cand) {
    bool complete = true;
    for (int k = 0; k < 3; ++k) {
      if (!p.has_axis(k)) continue;
      const PairedSample* e = rows.partner(k, i);
      if (e) ++matched[k];
      if (!e || e->reading_lost) complete = false;
    }
    if (complete) rows.row_of.push_back(i);
  }
  for (int k = 0; k < 3; ++k)
    if (p.has_axis(k) && k != first && !cand.empty() && matched[k] == 0)
      throw DataError(source + ": axis " + kAxisNames[k] + ": none of its " +
                      std::to_string(rows.paired[k].samples.size()) + " samples has the sequence number of a reading of axis " +
                      kAxisNames[first] + " within one sample period (" + std::to_string(rows.period) +
                      " s) of it: the axes were not recorded together");
}

// Each step of the rows longer than the sample clock (the median step of the first axis' readings; a gap does not
// move it) as one line naming where, how many samples and which axes lost them.
std::vector<std::string> describe_row_gaps(const AxisPresence& p, const JoinedRows& rows, const std::string& source) {
  std::vector<std::string> out;
  const std::size_t n = rows.row_of.size();
  if (n < 2) return out;
  const auto& first = rows.paired[rows.first].samples;
  std::vector<double> reading_s;
  for (std::uint32_t i : rows.candidates) reading_s.push_back(first[i].stamp_s);
  const double clock_s = median_step_s(reading_s);
  for (std::size_t r = 1; clock_s > 0.0 && r < n; ++r) {
    const double step = rows.t(r) - rows.t(r - 1);
    const long missing = std::lround(step / clock_s) - 1;
    if (missing < 1) continue;  // jitter
    // who lost them: per axis, the steps in between without a reading of it (stamps within half a step)
    const PairedSample& before = first[rows.row_of[r - 1]];
    long lacking[3] = {};
    for (int k = 0; k < 3; ++k) {
      if (!p.has_axis(k)) continue;
      long heard = 0;
      for (const auto& e : rows.paired[k].samples)
        heard += !e.reading_lost && e.stamp_s > before.stamp_s + 0.5 * clock_s && e.stamp_s < rows.t(r) - 0.5 * clock_s;
      lacking[k] = std::max(0L, missing - heard);
    }
    std::ostringstream os;
    os << source << ": " << missing << " sample(s) missing after t = " << std::fixed << std::setprecision(6)
       << before.stamp_s << " s (row " << r + 1 << ", sequence " << before.sequence << "): ";
    std::string sep;
    for (int k = 0; k < 3; ++k)
      if (lacking[k] > 0) os << sep << "axis " << kAxisNames[k] << " lost " << lacking[k], sep = ", ";
    os << "; a model steps over them as one sample, nothing is filled in";
    out.push_back(os.str());
  }
  return out;
}

// Each axis' columns from its paired samples at the rows.
void fill_axis_columns(const AxisPresence& p, const JoinedRows& rows, const std::string& source, Dataset& d) {
  const std::size_t n = rows.row_of.size();
  for (int k = 0; k < 3; ++k) {
    if (!p.has_axis(k)) continue;
    auto& ax = d.add_axis(kAxisNames[k]);
    const bool with_truth = p.truth[k];
    if (with_truth) ax.true_position_nm.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      const PairedSample* e = rows.partner(k, rows.row_of[i]);
      if (!e->measured)
        throw DataError(at_row_col(source, i, position_column(kAxisNames[k])) + "encoder reading flagged invalid");
      ax.position_nm[i] = e->position_nm;
      ax.voltage_v[i] = e->voltage_v;
      if (with_truth) {
        if (!std::isfinite(e->truth_nm))
          throw DataError(at_row_col(source, i, true_position_column(kAxisNames[k])) + "no message at or before t=" +
                          std::to_string(rows.t(i)) + " s");
        ax.true_position_nm[i] = e->truth_nm;
      }
    }
    if (rows.paired[k].dropped > 0)
      throw DataError(source + ": axis " + kAxisNames[k] + ": " + std::to_string(rows.paired[k].dropped) +
                      " encoder reading(s) with no voltage message at or before them");
  }
}

// Aux columns (the latest value at each row) and the protocol markers in force at each row.
void fill_aux_and_marker_columns(const RecordedMessages& m, const JoinedRows& rows, Dataset& d) {
  const std::size_t n = rows.row_of.size();
  for (const auto& [name, values] : m.aux) {
    AuxSignal s{name, std::vector<double>(n)};
    for (std::size_t i = 0; i < n; ++i) {
      const StampedValue* x = latest_at(values, rows.t(i), rows.period);
      if (!x) throw DataError(at_row_col(m.source, i, name) + "no aux message at or before t=" + std::to_string(rows.t(i)) + " s");
      s.values[i] = x->value;
    }
    d.aux.push_back(std::move(s));
  }
  const auto& markers = m.markers;
  if (markers.empty()) return;
  d.segment.resize(n);
  d.phase.resize(n);
  if (markers.front().first - rows.t(0) > rows.period)
    throw DataError(at_row_col(m.source, 0, "phase") + "the first protocol_phase marker comes after the first sample");
  std::size_t k = 0;
  for (std::size_t i = 0; i < n; ++i) {
    while (k + 1 < markers.size() && markers[k + 1].first <= rows.t(i) + 1e-9) ++k;
    d.segment[i] = markers[k].second.first;
    d.phase[i] = markers[k].second.second;
  }
}

}  // namespace

Dataset dataset_from_messages(RecordedMessages&& m, const MessageRowOptions& options) {
  AxisPresence p;
  for (int k = 0; k < 3; ++k) {
    p.voltage[k] = !m.axes[k].voltage.empty();
    p.encoder[k] = !m.axes[k].encoder.empty();
    p.truth[k] = !m.axes[k].truth.empty();
  }
  JoinedRows rows;
  rows.first = first_recorded_axis(p, m);
  for (auto& a : m.axes) sort_by_stamp(a.voltage), sort_by_stamp(a.encoder), sort_by_stamp(a.truth);
  for (auto& kv : m.aux) sort_by_stamp(kv.second);
  std::stable_sort(m.markers.begin(), m.markers.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
  // Each axis' voltage, reading and truth paired by the one rule the live nodes use (io/sequence_pairer.h),
  // fed in stamp order as the predictor would have heard them.
  for (int k = 0; k < 3; ++k) {
    if (!p.has_axis(k)) continue;
    rows.paired[k] = pair_axis_messages(m.axes[k]);
    m.axes[k] = AxisMessages();  // free what the pairing consumed
  }
  join_axis_rows(p, m.source, rows);
  if (options.gaps) *options.gaps = describe_row_gaps(p, rows, m.source);
  const std::size_t n = rows.row_of.size();
  Dataset d;
  d.source = m.source;
  d.time_clock = "ros";  // stamps are ROS time (sim time under use_sim_time)
  d.time_s.resize(n);
  for (std::size_t i = 0; i < n; ++i) d.time_s[i] = rows.t(i);
  if (options.row_sequences) {
    options.row_sequences->resize(n);
    for (std::size_t i = 0; i < n; ++i)
      (*options.row_sequences)[i] = rows.paired[rows.first].samples[rows.row_of[i]].sequence;
  }
  fill_axis_columns(p, rows, m.source, d);
  fill_aux_and_marker_columns(m, rows, d);
  return d;
}

}  // namespace piezo::io
