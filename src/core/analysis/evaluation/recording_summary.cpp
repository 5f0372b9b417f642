#include "piezo_compensation/analysis/evaluation/recording_summary.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/util/stats.h"

namespace piezo::analysis {

namespace {
constexpr std::uint64_t kWrap = std::uint64_t{1} << 32;
constexpr std::size_t kMaxListedGaps = 10000;  // counts stay exact; only the listing is capped
}  // namespace

SequenceTracker::SequenceTracker(std::uint32_t restart_threshold, std::uint32_t late_window)
    : restart_threshold_(restart_threshold), late_window_(late_window) {}

SequenceTracker::Arrival SequenceTracker::add(std::uint32_t sequence) {
  ++received_;
  if (!newest_) {
    newest_ = sequence;
    epoch_ = 0;
    return Arrival::kFirst;
  }
  const std::uint64_t newest_unwrapped = epoch_ + *newest_;
  const std::int64_t d = static_cast<std::int32_t>(sequence - *newest_);  // signed distance, wrap-safe

  auto retire_old = [&](std::uint64_t keep_from) {
    // missing numbers older than the late window: no longer expected, listed as old gaps
    while (!missing_recent_.empty() && *missing_recent_.begin() < keep_from) {
      const std::uint64_t x = *missing_recent_.begin();
      missing_recent_.erase(missing_recent_.begin());
      const std::uint32_t x32 = static_cast<std::uint32_t>(x % kWrap);
      if (!old_gaps_.empty() &&
          static_cast<std::uint32_t>(old_gaps_.back().first_missing + old_gaps_.back().count) == x32)
        ++old_gaps_.back().count;
      else if (old_gaps_.size() < kMaxListedGaps)
        old_gaps_.push_back({x32, 1});
    }
  };

  if (d == 1) {
    newest_ = sequence;
    if (sequence == 0) epoch_ += kWrap;
    retire_old(newest_unwrapped + 1 > late_window_ ? newest_unwrapped + 1 - late_window_ : 0);
    return Arrival::kInOrder;
  }
  if (d > 1) {
    const std::uint64_t first = newest_unwrapped + 1;
    const std::uint64_t last = newest_unwrapped + static_cast<std::uint64_t>(d) - 1;  // inclusive
    dropped_ += last - first + 1;
    const std::uint64_t new_newest = newest_unwrapped + static_cast<std::uint64_t>(d);
    const std::uint64_t keep_from = new_newest > late_window_ ? new_newest - late_window_ : 0;
    retire_old(keep_from);
    if (first < keep_from) {  // the part of a huge gap that can no longer arrive late
      const std::uint64_t old_last = std::min(last, keep_from - 1);
      if (old_gaps_.size() < kMaxListedGaps)
        old_gaps_.push_back({static_cast<std::uint32_t>(first % kWrap), old_last - first + 1});
    }
    for (std::uint64_t x = std::max(first, keep_from); x <= last; ++x) missing_recent_.insert(x);
    epoch_ = new_newest - (new_newest % kWrap);
    newest_ = sequence;
    return Arrival::kGap;
  }
  // d <= 0: older than (or equal to) the newest
  if (-d > static_cast<std::int64_t>(restart_threshold_)) {
    ++restarts_;
    retire_old(UINT64_MAX);
    // continue unwrapping above everything seen so far so numbers stay unique
    epoch_ = (newest_unwrapped / kWrap + 1) * kWrap;
    newest_ = sequence;
    return Arrival::kRestart;
  }
  const std::uint64_t x = newest_unwrapped - static_cast<std::uint64_t>(-d);
  auto it = missing_recent_.find(x);
  if (it != missing_recent_.end()) {
    missing_recent_.erase(it);
    --dropped_;
    ++late_;
    return Arrival::kLate;
  }
  ++duplicates_;
  return Arrival::kDuplicate;
}

std::vector<SequenceGap> SequenceTracker::gaps() const {
  std::vector<SequenceGap> out = old_gaps_;
  std::optional<std::uint64_t> run_start;
  std::uint64_t run_last = 0;
  auto flush = [&] {
    if (run_start && out.size() < kMaxListedGaps)
      out.push_back({static_cast<std::uint32_t>(*run_start % kWrap), run_last - *run_start + 1});
  };
  for (std::uint64_t x : missing_recent_) {
    if (run_start && x == run_last + 1) {
      run_last = x;
      continue;
    }
    flush();
    run_start = x;
    run_last = x;
  }
  flush();
  return out;
}

SequenceReport report_of(const std::string& axis, const SequenceTracker& t) {
  SequenceReport r;
  r.axis = axis;
  r.received = t.received();
  r.dropped = t.dropped();
  r.out_of_order = t.out_of_order();
  r.duplicates = t.duplicates();
  r.restarts = t.restarts();
  r.gaps = t.gaps();
  return r;
}

SequenceReport analyze_sequences(const std::string& axis, const std::vector<std::uint32_t>& sequence) {
  SequenceTracker t;
  for (std::uint32_t s : sequence) t.add(s);
  return report_of(axis, t);
}

ContinuityReport check_continuity(const std::vector<double>& time_s) {
  ContinuityReport r;
  if (time_s.size() < 2) return r;
  std::vector<double> steps(time_s.size() - 1);
  for (std::size_t i = 1; i < time_s.size(); ++i) steps[i - 1] = time_s[i] - time_s[i - 1];
  r.period_s = util::median(steps);
  if (!(r.period_s > 0.0)) return r;
  for (std::size_t i = 0; i < steps.size(); ++i) {
    bool problem = false;
    if (steps[i] < 0.5 * r.period_s) {
      ++r.duplicated_samples;
      problem = true;
    } else if (steps[i] > 1.5 * r.period_s) {
      r.lost_samples += static_cast<std::size_t>(std::llround(steps[i] / r.period_s)) - 1;
      problem = true;
    }
    if (problem && r.problem_rows.size() < 100) r.problem_rows.push_back(i + 1);
  }
  return r;
}

VoltageMatch compare_voltages(const io::Dataset& recorded, const io::Dataset& program, double tolerance_v) {
  VoltageMatch m;
  const std::size_t n = std::min(recorded.size(), program.size());
  for (std::size_t i = 0; i < n; ++i) {
    bool bad = false;
    for (const auto& a : recorded.axes) {
      if (!program.has_axis(a.name)) continue;
      const double err = std::fabs(a.voltage_v[i] - program.axis(a.name).voltage_v[i]);
      m.max_abs_error_v = std::max(m.max_abs_error_v, err);
      if (!(err <= tolerance_v)) bad = true;
    }
    if (bad && m.mismatched++ == 0) m.first_mismatch = i;
    ++m.compared;
  }
  return m;
}

std::vector<NoiseEstimate> estimate_noise(const io::Dataset& data) {
  const std::string where = data.source.empty() ? std::string("data set") : data.source;
  if (data.phase.size() != data.size())
    throw io::DataError(where + ": no phase column, so no record windows to estimate the encoder noise from");
  const int record = static_cast<int>(protocols::Phase::kRecord);
  std::vector<std::pair<std::size_t, std::size_t>> windows;  // [begin, end)
  for (std::size_t i = 0; i < data.size();) {
    if (data.phase[i] != record) {
      ++i;
      continue;
    }
    std::size_t j = i;
    while (j < data.size() && data.phase[j] == record &&
           (data.segment.size() != data.size() || data.segment[j] == data.segment[i]))
      ++j;
    if (j - i >= 3) windows.emplace_back(i, j);
    i = j;
  }
  if (windows.empty())
    throw io::DataError(where + ": no record-phase window of 3 or more samples (phase code " +
                        std::to_string(record) + "), so no encoder noise estimate");
  std::vector<NoiseEstimate> out;
  for (const auto& axis : data.axes) {
    NoiseEstimate e;
    e.axis = axis.name;
    double ss_total = 0.0;
    std::size_t dof_total = 0;
    for (const auto& [b, en] : windows) {
      // least-squares line through (t, x), on centred time for conditioning
      const std::size_t n = en - b;
      double tm = 0, xm = 0, vm = 0;
      for (std::size_t i = b; i < en; ++i) {
        tm += data.time_s[i];
        xm += axis.position_nm[i];
        vm += axis.voltage_v[i];
      }
      tm /= n;
      xm /= n;
      vm /= n;
      double stt = 0, stx = 0;
      for (std::size_t i = b; i < en; ++i) {
        stt += (data.time_s[i] - tm) * (data.time_s[i] - tm);
        stx += (data.time_s[i] - tm) * (axis.position_nm[i] - xm);
      }
      const double slope = stt > 0 ? stx / stt : 0.0;
      double ss = 0;
      for (std::size_t i = b; i < en; ++i) {
        const double r = axis.position_nm[i] - xm - slope * (data.time_s[i] - tm);
        ss += r * r;
      }
      for (std::size_t i = b + 1; i < en; ++i) {
        const double step = std::fabs(axis.position_nm[i] - axis.position_nm[i - 1]);
        if (step > 1e-9 && (e.resolution_nm == 0.0 || step < e.resolution_nm)) e.resolution_nm = step;
      }
      e.window_sigma_nm.push_back(std::sqrt(ss / static_cast<double>(n - 2)));
      e.window_voltage_v.push_back(vm);
      ss_total += ss;
      dof_total += n - 2;
      e.samples += n;
    }
    e.sigma_nm = std::sqrt(ss_total / static_cast<double>(dof_total));
    out.push_back(std::move(e));
  }
  return out;
}

RecordingSummary summarize(const io::Dataset& data, const std::string& protocol, const io::Dataset* program,
                           double voltage_tolerance_v) {
  RecordingSummary s;
  s.protocol = protocol;
  s.samples = data.size();
  if (data.size() >= 2) {
    s.duration_s = data.time_s.back() - data.time_s.front();
    s.continuity = check_continuity(data.time_s);
    if (s.continuity.period_s > 0) s.sample_rate_hz = 1.0 / s.continuity.period_s;
  }
  const int record = static_cast<int>(protocols::Phase::kRecord);
  if (data.phase.size() == data.size() && std::count(data.phase.begin(), data.phase.end(), record) >= 3) {
    try {
      s.noise = estimate_noise(data);
    } catch (const io::DataError&) {
      // record rows too fragmented for a window: no estimate, the summary says none
    }
  }
  if (program) s.voltages = compare_voltages(data, *program, voltage_tolerance_v);
  return s;
}

std::string format_summary(const RecordingSummary& s) {
  std::ostringstream os;
  os << std::setprecision(6);
  os << "recording" << (s.protocol.empty() ? "" : " of protocol " + s.protocol) << ": " << s.samples
     << " samples, " << s.duration_s << " s";
  if (s.sample_rate_hz > 0) os << " at " << s.sample_rate_hz << " Hz";
  os << "\n";
  os << "  time gaps: " << s.continuity.lost_samples << " lost, " << s.continuity.duplicated_samples
     << " duplicated samples";
  if (!s.continuity.problem_rows.empty()) {
    os << " (rows";
    for (std::size_t i = 0; i < std::min<std::size_t>(10, s.continuity.problem_rows.size()); ++i)
      os << " " << s.continuity.problem_rows[i];
    if (s.continuity.problem_rows.size() > 10) os << " ...";
    os << ")";
  }
  os << "\n";
  for (const auto& q : s.sequences) {
    os << "  encoder " << q.axis << ": " << q.received << " received, " << q.dropped << " dropped, "
       << q.out_of_order << " out of order, " << q.duplicates << " duplicated";
    if (q.restarts) os << ", " << q.restarts << " counter restarts";
    os << "\n";
    for (std::size_t i = 0; i < std::min<std::size_t>(20, q.gaps.size()); ++i)
      os << "    missing sequence " << q.gaps[i].first_missing
         << (q.gaps[i].count > 1 ? " .. " + std::to_string(q.gaps[i].first_missing + q.gaps[i].count - 1) : "")
         << " (" << q.gaps[i].count << ")\n";
    if (q.gaps.size() > 20) os << "    ... " << q.gaps.size() - 20 << " more gaps\n";
  }
  if (s.voltages) {
    os << "  voltage pattern: " << s.voltages->compared << " samples compared, " << s.voltages->mismatched
       << " differ from the protocol (max |error| " << s.voltages->max_abs_error_v << " V";
    if (s.voltages->mismatched) os << ", first at row " << s.voltages->first_mismatch;
    os << ")\n";
  }
  for (const auto& n : s.noise) {
    os << "  encoder noise " << n.axis << ": sigma " << std::setprecision(4) << n.sigma_nm << " nm over "
       << n.samples << " samples in " << n.window_sigma_nm.size() << " windows (";
    for (std::size_t i = 0; i < n.window_sigma_nm.size(); ++i)
      os << (i ? ", " : "") << std::setprecision(3) << n.window_voltage_v[i] << " V: " << n.window_sigma_nm[i]
         << " nm";
    os << ")";
    if (n.below_resolution())
      os << " -- below the encoder step of " << n.resolution_nm << " nm: not a measurable noise";
    os << "\n" << std::setprecision(6);
  }
  return os.str();
}

}  // namespace piezo::analysis
