#include "piezo_compensation/compensation/reload_warmup.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>

#include "piezo_compensation/compensation/base_handover.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/message_rows.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::compensation {

namespace {

// AugmentedModel::set_base_trace for one scope: the trace is cleared on every way out (a stream that throws too).
class BaseTraceScope {
 public:
  BaseTraceScope(models::AugmentedModel* m, std::vector<double>* trace) : m_(m) {
    if (m_) m_->set_base_trace(trace);
  }
  ~BaseTraceScope() {
    if (m_) m_->set_base_trace(nullptr);
  }
  BaseTraceScope(const BaseTraceScope&) = delete;
  BaseTraceScope& operator=(const BaseTraceScope&) = delete;

 private:
  models::AugmentedModel* m_;
};

// One stream of the snapshot as the bag reader meets it: in the order heard (the bag's record time), then sorted by
// stamp by the row rule.
template <class T, class Make>
std::vector<io::StampedValue> heard_in_order(const std::vector<T>& xs, Make make) {
  std::vector<const T*> order;
  order.reserve(xs.size());
  for (const auto& x : xs) order.push_back(&x);
  std::stable_sort(order.begin(), order.end(), [](const T* a, const T* b) { return a->received_s < b->received_s; });
  std::vector<io::StampedValue> out;
  out.reserve(xs.size());
  for (const T* x : order) out.push_back(make(*x));
  return out;
}

// The running base's recorded prediction per row of `d` (NaN where none). Row i is the sample with sequence
// number row_seq[i] on every axis (the reader's pairing); a sample another axis lost has no row, so matching by
// index would shift every later row. A controller restart reuses numbers: of equal numbers, the axis' reading on
// the sample clock nearest the row, and the prediction stamped nearest its receive stamp (the same stamp).
std::vector<double> running_base_per_row(const Snapshot::Axis& ax, const io::Dataset& d,
                                         const std::vector<std::uint32_t>& row_seq) {
  constexpr double kSameSampleS = 1.0;  // as SnapshotBuffer::take pairs a report with its reading
  std::vector<double> base(d.size(), std::nan(""));
  if (row_seq.size() != d.size()) return base;
  // the one with number `seq` whose stamp(x) is nearest t, within kSameSampleS, or null
  const auto nearest = [](const auto& by_seq, std::uint32_t seq, double t, auto stamp) {
    const auto [lo, hi] = by_seq.equal_range(seq);
    decltype(lo->second) found = nullptr;
    double best = kSameSampleS;
    for (auto it = lo; it != hi; ++it)
      if (const double dt = std::fabs(stamp(*it->second) - t); dt <= best) best = dt, found = it->second;
    return found;
  };
  std::multimap<std::uint32_t, const SnapshotReading*> readings;
  std::multimap<std::uint32_t, const SnapshotPrediction*> predictions;
  for (const auto& r : ax.readings) readings.emplace(r.sequence, &r);
  for (const auto& p : ax.base_predictions) predictions.emplace(p.sequence, &p);
  for (std::size_t i = 0; i < d.size(); ++i) {
    const auto* r = nearest(readings, row_seq[i], d.time_s[i], [](const auto& x) { return x.stamp_s; });
    const auto* p = r ? nearest(predictions, row_seq[i], r->received_s, [](const auto& x) { return x.stamp_s; }) : nullptr;
    if (p) base[i] = p->base_nm;
  }
  return base;
}

std::string describe_handover(const BaseHandover& h, const Snapshot::Axis& ax, const std::string& axis,
                              std::size_t rows) {
  std::ostringstream os;
  if (h.done)
    os << "base state from the running model, offset " << std::showpos << h.offset_change_nm << std::noshowpos
       << " nm on " << h.samples << " samples";
  else
    os << "base warmed from rest (" << h.why << ")";
  // readings of this axis without a row: samples another axis lost or has not yet (the reader fills none); the
  // rest are matched by sequence number, so they cost only their own rows
  if (ax.readings.size() > rows)
    os << " (" << ax.readings.size() - rows << " of " << axis << "'s " << ax.readings.size()
       << " readings have no row, their sample missing on another axis; rows matched by sequence number)";
  return os.str();
}

}  // namespace

io::Dataset snapshot_dataset(const Snapshot& s, std::vector<std::uint32_t>* row_sequences) {
  io::RecordedMessages m;
  m.source = "snapshot buffer";
  for (const auto& [axis, a] : s.axes) {
    const int k = io::axis_index_or_none(axis);
    if (k < 0) throw io::DataError("snapshot buffer: axis '" + axis + "' is not one of a, b, c");
    m.axes[k].voltage = heard_in_order(a.voltages, [](const SnapshotVoltage& x) {
      return io::StampedValue{x.stamp_s, x.sequence, x.voltage_v, true};
    });
    // invalid readings are not in the snapshot (Snapshot::invalid_readings)
    m.axes[k].encoder = heard_in_order(a.readings, [](const SnapshotReading& x) {
      return io::StampedValue{x.stamp_s, x.sequence, x.position_nm, true};
    });
  }
  for (const auto& [name, values] : s.aux) {
    auto& out = m.aux[name];
    for (const auto& x : values) out.push_back({x.stamp_s, 0, x.value, true});
    std::stable_sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.stamp_s < b.stamp_s; });
  }
  io::MessageRowOptions o;
  o.row_sequences = row_sequences;
  return io::dataset_from_messages(std::move(m), o);
}

std::string warm_model(models::Model& model, const std::string& axis, const Snapshot& s,
                       const models::Model* running, std::string* handover) {
  if (!s.axes.count(axis)) return "axis " + axis + " not in the buffer";
  try {
    std::vector<std::uint32_t> row_seq;
    const io::Dataset d = snapshot_dataset(s, &row_seq);
    // on failure the reload resets it (cold)
    auto* aug = dynamic_cast<models::AugmentedModel*>(&model);
    const bool hand_over = running && aug && handover;
    std::vector<double> warm, warm_base;  // the hand-over takes the base part from this one stream
    {
      const BaseTraceScope trace(hand_over ? aug : nullptr, &warm_base);
      warm = models::stream_model(model, d, axis, models::StreamOptions{}).prediction;
    }
    if (hand_over) {
      const auto& ax = s.axes.at(axis);
      const std::vector<double> base = running_base_per_row(ax, d, row_seq);
      const BaseHandover h = hand_over_base(*aug, *running, d, axis, warm, warm_base, base);
      *handover = describe_handover(h, ax, axis, d.size());
    }
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

}  // namespace piezo::compensation
