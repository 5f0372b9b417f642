#include "piezo_compensation/io/sequence_pairer.h"

#include <algorithm>

namespace piezo::io {
SequencePairer::SequencePairer(PairerOptions options) : o_(options) {
  if (o_.keep_reports < 2) o_.keep_reports = 2;
}

void SequencePairer::clear() {
  voltages_.clear();
  truths_.clear();
  pending_.clear();
  last_emitted_.reset();
  newest_reading_.reset();
}

void SequencePairer::remember(std::deque<Report>& q, std::uint32_t seq, double value, double stamp_s) {
  for (auto& r : q)
    if (r.seq == seq) {
      r.value = value, r.stamp_s = stamp_s;  // a repeated report: the newer value counts
      return;
    }
  q.push_back({seq, value, stamp_s});
  while (q.size() > o_.keep_reports) q.pop_front();
}

bool SequencePairer::restarted(std::optional<std::uint32_t> newest, std::uint32_t seq) const {
  return newest && static_cast<std::int32_t>(*newest - seq) > static_cast<std::int32_t>(o_.restart_threshold);
}

void SequencePairer::restart(std::vector<PairedSample>& out, std::uint32_t seq) {
  drain(out, true);  // what is pending belongs to the old numbering
  pending_.clear();
  const auto old = [&](const Report& r) {
    return static_cast<std::int32_t>(r.seq - seq) > static_cast<std::int32_t>(o_.restart_threshold);
  };
  voltages_.erase(std::remove_if(voltages_.begin(), voltages_.end(), old), voltages_.end());
  truths_.erase(std::remove_if(truths_.begin(), truths_.end(), old), truths_.end());
  last_emitted_.reset();
  newest_reading_.reset();
  ++counters_.restarts;
}

std::vector<PairedSample> SequencePairer::add_voltage(std::uint32_t seq, double voltage_v, double stamp_s) {
  std::vector<PairedSample> out;
  if (restarted(voltages_.empty() ? std::nullopt : std::optional<std::uint32_t>(voltages_.back().seq), seq))
    restart(out, seq);
  remember(voltages_, seq, voltage_v, stamp_s);
  drain(out, false);
  return out;
}

std::vector<PairedSample> SequencePairer::add_truth(std::uint32_t seq, double truth_nm, double stamp_s) {
  std::vector<PairedSample> out;
  if (restarted(truths_.empty() ? std::nullopt : std::optional<std::uint32_t>(truths_.back().seq), seq))
    restart(out, seq);
  remember(truths_, seq, truth_nm, stamp_s);
  drain(out, false);
  return out;
}

std::vector<PairedSample> SequencePairer::add_reading(std::uint32_t seq, double position_nm, bool valid,
                                                      double stamp_s) {
  std::vector<PairedSample> out;
  if (restarted(newest_reading_, seq)) restart(out, seq);
  if (last_emitted_ && !sequence_newer(seq, *last_emitted_)) {
    ++counters_.late_readings;
    return out;
  }
  auto it = std::find_if(pending_.begin(), pending_.end(), [&](const Reading& r) { return !sequence_newer(seq, r.seq); });
  if (it != pending_.end() && it->seq == seq) {
    *it = {seq, position_nm, stamp_s, valid};  // repeated: the newer reading counts
  } else {
    pending_.insert(it, {seq, position_nm, stamp_s, valid});
  }
  if (!newest_reading_ || sequence_newer(seq, *newest_reading_)) newest_reading_ = seq;
  drain(out, false);
  return out;
}

std::vector<PairedSample> SequencePairer::flush() {
  std::vector<PairedSample> out;
  drain(out, true);
  return out;
}

void SequencePairer::emit_lost_readings(std::vector<PairedSample>& out, std::uint32_t seq) {
  if (!last_emitted_) return;
  const auto gap = static_cast<std::uint32_t>(seq - *last_emitted_ - 1);
  counters_.lost_readings += gap;
  if (gap > o_.keep_reports) return;  // far more than any report we remember
  const auto by_seq = [](const Report& r) { return r.seq; };
  for (std::uint32_t s = *last_emitted_ + 1; s != seq; ++s) {
    const Report* v = nullptr;
    if (match_report(voltages_, s, false, by_seq, &v) != ReportMatch::kFound) continue;
    PairedSample p;
    p.sequence = s;
    p.stamp_s = v->stamp_s;
    p.voltage_v = v->value;
    p.reading_lost = true;
    if (o_.with_truth) {
      const Report* t = nullptr;
      if (match_report(truths_, s, false, by_seq, &t) == ReportMatch::kFound) p.truth_nm = t->value;
      else p.truth_lost = true;
    }
    ++counters_.samples;
    out.push_back(p);
  }
}

void SequencePairer::drain(std::vector<PairedSample>& out, bool give_up_all) {
  const auto by_seq = [](const Report& r) { return r.seq; };
  while (!pending_.empty()) {
    const Reading head = pending_.front();
    const bool give_up = give_up_all || pending_.size() > o_.max_pending;
    const Report* v = nullptr;
    const Report* t = nullptr;
    const ReportMatch vm = match_report(voltages_, head.seq, give_up, by_seq, &v);
    if (vm == ReportMatch::kWaiting) return;
    ReportMatch tm = ReportMatch::kFound;
    if (o_.with_truth) {
      tm = match_report(truths_, head.seq, give_up, by_seq, &t);
      if (tm == ReportMatch::kWaiting) return;
    }
    emit_lost_readings(out, head.seq);
    pending_.pop_front();
    last_emitted_ = head.seq;
    if (!v) {  // lost, and nothing held before it is known
      ++counters_.dropped_samples;
      continue;
    }
    PairedSample p;
    p.sequence = head.seq;
    p.stamp_s = head.stamp_s;
    p.voltage_v = v->value;
    p.voltage_lost = vm == ReportMatch::kLost;
    p.measured = head.valid && std::isfinite(head.position_nm);
    p.position_nm = head.position_nm;
    if (o_.with_truth) {
      p.truth_lost = tm == ReportMatch::kLost;
      p.truth_nm = t ? t->value : std::nan("");
      counters_.lost_truths += p.truth_lost;
    }
    counters_.lost_voltages += p.voltage_lost;
    ++counters_.samples;
    out.push_back(p);
  }
}

}  // namespace piezo::io
