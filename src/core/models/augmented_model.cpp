#include "piezo_compensation/models/augmented_model.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/util/format.h"

namespace piezo::models {

namespace {
constexpr double kTwoPi = 6.283185307179586;

bool is_builtin_signal(const std::string& s) { return s == kSignalVoltage || s == kSignalPosition; }

std::string fmt(double v) { return util::fmt(v, 4); }

double yaml_num(const YAML::Node& n, const char* key, double def) {
  if (!n[key]) return def;
  try {
    const double v = n[key].as<double>();
    if (!std::isfinite(v)) throw std::runtime_error("");
    return v;
  } catch (const std::exception&) {
    throw std::runtime_error(std::string("augmented model term: key '") + key + "' is not a finite number");
  }
}

std::vector<double> yaml_vec(const YAML::Node& n, const char* key) {
  std::vector<double> v;
  if (!n[key]) return v;
  if (!n[key].IsSequence()) throw std::runtime_error(std::string("augmented model term: key '") + key + "' is not a list");
  for (const auto& x : n[key]) {
    const double d = x.as<double>();
    if (!std::isfinite(d)) throw std::runtime_error(std::string("augmented model term: '") + key + "' holds a non-finite value");
    v.push_back(d);
  }
  return v;
}
}  // namespace

namespace {
constexpr std::pair<const char*, TermKind> kTermKinds[] = {
    {"linear", TermKind::kLinear}, {"play", TermKind::kPlay},       {"sincos", TermKind::kSinCos},
    {"rate", TermKind::kRate},     {"powers", TermKind::kPowers},   {"gain", TermKind::kGain},
    {"gain_quadratic", TermKind::kGainQuadratic}};
}  // namespace

TermKind term_kind(const std::string& type) {
  for (const auto& [name, kind] : kTermKinds)
    if (type == name) return kind;
  throw std::runtime_error("augmented model term: unknown type '" + type +
                           "' (linear, play, sincos, rate, powers, gain, gain_quadratic)");
}

const char* term_kind_name(TermKind kind) {
  for (const auto& [name, k] : kTermKinds)
    if (k == kind) return name;
  return "?";
}

std::size_t EffectTerm::num_regressors() const {
  switch (kind()) {
    case TermKind::kSinCos:
    case TermKind::kPowers:
    case TermKind::kGainQuadratic: return 2;
    case TermKind::kRate: return 3;
    default: return 1;  // linear, play, gain
  }
}

std::string EffectTerm::name() const {
  std::ostringstream os;
  os << type << "(" << signal;
  if (lag_s > 0) os << ", lag " << fmt(lag_s) << " s";
  if (kind() == TermKind::kPlay) os << ", r=" << fmt(threshold);
  if (kind() == TermKind::kSinCos) os << ", period " << fmt(period) << (signal == kSignalTime ? " s" : signal == kSignalPosition ? " nm" : "");
  if (time_constant_s > 0) os << ", low-pass " << fmt(time_constant_s) << " s";
  if (is_gain()) os << ", scales " << scales;
  if (in_readings()) os << ", in the readings";
  os << ")";
  return os.str();
}

YAML::Node EffectTerm::to_yaml() const {
  YAML::Node n;
  n["type"] = type;
  n["signal"] = signal;
  n["family"] = family;
  n["lag_s"] = lag_s;
  n["time_constant_s"] = time_constant_s;
  n["threshold"] = threshold;
  n["period"] = period;
  n["pre_center"] = pre_center;
  n["pre_scale"] = pre_scale;
  if (is_gain()) {
    n["scales"] = scales;
    n["reference"] = reference;
  }
  if (in_readings()) n["acts_on"] = acts_on;
  for (double c : center) n["center"].push_back(c);
  for (double s : scale) n["scale"].push_back(s);
  for (double w : weight) n["weight"].push_back(w);
  return n;
}

EffectTerm EffectTerm::from_yaml(const YAML::Node& n) {
  if (!n.IsMap()) throw std::runtime_error("augmented model: a term is not a map");
  for (const auto& kv : n) {
    static const char* known[] = {"type", "signal", "family", "lag_s", "time_constant_s", "threshold", "period",
                                  "pre_center", "pre_scale", "center", "scale", "weight", "scales", "reference", "acts_on"};
    const std::string k = kv.first.as<std::string>();
    if (std::find_if(std::begin(known), std::end(known), [&](const char* s) { return k == s; }) == std::end(known))
      throw std::runtime_error("augmented model term: unknown key '" + k + "'");
  }
  EffectTerm t;
  if (!n["type"] || !n["signal"]) throw std::runtime_error("augmented model term: needs 'type' and 'signal'");
  t.type = n["type"].as<std::string>();
  t.signal = n["signal"].as<std::string>();
  if (n["family"]) t.family = n["family"].as<std::string>();
  t.lag_s = yaml_num(n, "lag_s", 0.0);
  t.time_constant_s = yaml_num(n, "time_constant_s", 0.0);
  t.threshold = yaml_num(n, "threshold", 0.0);
  t.period = yaml_num(n, "period", 0.0);
  t.pre_center = yaml_num(n, "pre_center", 0.0);
  t.pre_scale = yaml_num(n, "pre_scale", 1.0);
  if (n["scales"]) t.scales = n["scales"].as<std::string>();
  t.reference = yaml_num(n, "reference", 0.0);
  if (n["acts_on"]) t.acts_on = n["acts_on"].as<std::string>();
  if (t.acts_on != kActsOnPosition && t.acts_on != kActsOnReadings)
    throw std::runtime_error("augmented model term " + t.name() + ": 'acts_on' must be position or readings, got '" + t.acts_on + "'");
  t.center = yaml_vec(n, "center");
  t.scale = yaml_vec(n, "scale");
  t.weight = yaml_vec(n, "weight");
  const std::size_t k = t.num_regressors();  // validates type
  if (t.center.size() != k || t.scale.size() != k || t.weight.size() != k)
    throw std::runtime_error("augmented model term " + t.name() + ": center/scale/weight need " + std::to_string(k) + " entries each");
  if (t.lag_s < 0 || t.time_constant_s < 0 || t.threshold < 0)
    throw std::runtime_error("augmented model term " + t.name() + ": lag_s, time_constant_s and threshold must be >= 0");
  if (t.kind() == TermKind::kSinCos && !(t.period > 0)) throw std::runtime_error("augmented model term " + t.name() + ": period must be > 0");
  if (t.is_gain() && t.scales != kSignalPosition && t.scales != kSignalVoltage)
    throw std::runtime_error("augmented model term " + t.name() + ": 'scales' must be position or voltage");
  if (t.pre_scale == 0.0) throw std::runtime_error("augmented model term " + t.name() + ": pre_scale must be non-zero");
  for (double s : t.scale)
    if (s == 0.0) throw std::runtime_error("augmented model term " + t.name() + ": scale must be non-zero");
  return t;
}

// ---- streaming terms -------------------------------------------------------------------------------
// The streaming terms' state, in a named namespace: EffectTermStream::Impl holds it, and a class of external
// linkage may not have fields of an anonymous namespace's types.
namespace effect_stream {
struct TermState {
  bool fresh = true;
  std::vector<double> ring;  // last L values of the signal, ring[pos] is the oldest
  std::size_t pos = 0;
  double lp[3] = {0, 0, 0};
  double play = 0.0;
  double prev = 0.0;
  double decay = 1.0;  // rate terms: α^n after n steps, the weight the zero start still has in lp
};

// What a term's strings say, resolved once when the stream is built (the per-sample loop compares no strings).
struct TermConst {
  std::size_t lag = 0;   // samples
  double alpha = 0.0;    // low-pass pole (0 = none)
  int column = -1;       // index into the column array, -1 = builtin
  TermKind kind = TermKind::kLinear;
  bool on_position = false;    // the term reads the (corrected) position
  bool scales_voltage = false; // a gain scales the voltage, not the base output
  bool in_readings = false;    // a sensor term (acts_on: readings)
  std::size_t regressors = 1;
};
}  // namespace effect_stream
using effect_stream::TermConst;
using effect_stream::TermState;

namespace {

// Evaluates one term for the current signal value s; writes the raw regressors and, if next != null, the
// state after committing s.
void eval_term(const EffectTerm& t, const TermConst& c, const TermState& st, double s, double q, double* out,
               TermState* next) {
  double lagged = s;
  if (c.lag > 0 && !st.fresh) lagged = st.ring[st.pos];
  auto lowpass = [&](int i, double x) {
    if (c.alpha <= 0.0) return x;
    const double prev = st.fresh ? x : st.lp[i];
    return c.alpha * prev + (1.0 - c.alpha) * x;
  };
  double lp_new[3] = {0, 0, 0};
  double play_new = st.play;
  if (c.kind == TermKind::kLinear) {
    out[0] = lp_new[0] = lowpass(0, lagged);
  } else if (c.kind == TermKind::kPlay) {
    const double prev = st.fresh ? lagged : st.play;
    play_new = std::max(lagged - t.threshold, std::min(lagged + t.threshold, prev));
    out[0] = lp_new[0] = lowpass(0, play_new);
  } else if (c.kind == TermKind::kSinCos) {
    const double ph = kTwoPi * lagged / t.period;
    out[0] = std::sin(ph);
    out[1] = std::cos(ph);
  } else if (c.kind == TermKind::kRate) {
    // The low-passed steps start from zero and are divided by 1 − αⁿ (a debiased mean): from the first step on
    // they estimate the recent step statistics. Not debiased, |ΔV| would rise from zero over a few τ, a start-up
    // decay a fit can trade against the base's start transients and then carry as an offset once settled
    // (docs/validation/residual-loop.md, "Live loop").
    double decay_new = st.decay;
    if (st.fresh) {
      for (int i = 0; i < 3; ++i) out[i] = lp_new[i] = 0.0;  // no step yet: nothing is known
    } else {
      const double d = s - st.prev;
      const double raw[3] = {d, std::fabs(d), d * std::fabs(d)};
      const double a = c.alpha;  // 0 without a time constant: the raw step
      decay_new = st.decay * a;
      for (int i = 0; i < 3; ++i) {
        lp_new[i] = a * st.lp[i] + (1.0 - a) * raw[i];
        out[i] = lp_new[i] / (1.0 - decay_new);
      }
    }
    if (next) next->decay = decay_new;
  } else if (c.kind == TermKind::kGain || c.kind == TermKind::kGainQuadratic) {
    const double g = (lowpass(0, lagged) - t.pre_center) / t.pre_scale;
    lp_new[0] = lowpass(0, lagged);
    out[0] = (q - t.reference) * g;
    if (c.kind == TermKind::kGainQuadratic) out[1] = (q - t.reference) * g * g;
  } else {  // powers
    const double u = (s - t.pre_center) / t.pre_scale;
    out[0] = u * u;
    out[1] = u * u * u;
  }
  if (next) {  // only the scalars; the caller advances the ring buffer
    for (int i = 0; i < 3; ++i) next->lp[i] = lp_new[i];
    next->play = play_new;
    next->prev = s;
  }
}
}  // namespace

struct EffectTermStream::Impl {
  std::vector<EffectTerm> terms;
  std::vector<TermConst> consts;
  std::vector<TermState> states;
  std::vector<std::string> columns;
  std::vector<std::size_t> first;  // first regressor index of each term
  std::size_t k = 0;
  double offset_nm = 0.0;

  // One pass over all terms: raw regressors into out (may be null), returns the correction; commits if asked.
  // Non-position terms first, then position terms at the corrected position.
  double run(double v, double x_base, const double* cols, double* out, std::vector<TermState>* commit,
             double* readings = nullptr) const {
    double local[3] = {0, 0, 0};
    double corr = offset_nm;
    if (readings) *readings = 0.0;
    for (int pass = 0; pass < 2; ++pass) {
      const double x_eff = x_base + corr;
      for (std::size_t i = 0; i < terms.size(); ++i) {
        const EffectTerm& t = terms[i];
        const bool pos = consts[i].on_position;
        if (pos != (pass == 1)) continue;
        const int c = consts[i].column;
        const double s = c >= 0 ? cols[c] : (pos ? x_eff : v);
        // A gain scales the base output (not the corrected one, which would make it recursive) or the voltage.
        const double q = consts[i].scales_voltage ? v : x_base;
        double* o = out ? out + first[i] : local;
        TermState next;
        eval_term(t, consts[i], states[i], s, q, o, commit ? &next : nullptr);
        if (commit) {
          TermState& st = (*commit)[i];
          const std::size_t lag = consts[i].lag;
          if (lag > 0) {
            if (st.fresh) std::fill(st.ring.begin(), st.ring.end(), s);
            st.ring[st.pos] = s;
            if (++st.pos == lag) st.pos = 0;
          }
          for (int q = 0; q < 3; ++q) st.lp[q] = next.lp[q];
          st.play = next.play;
          st.prev = next.prev;
          st.decay = next.decay;
          st.fresh = false;
        }
        double part = 0.0;
        for (std::size_t r = 0; r < consts[i].regressors; ++r) {
          const double z = (o[r] - (r < t.center.size() ? t.center[r] : 0.0)) / (r < t.scale.size() ? t.scale[r] : 1.0);
          part += (r < t.weight.size() ? t.weight[r] : 0.0) * z;
        }
        corr += part;
        if (readings && consts[i].in_readings) *readings += part;
      }
    }
    return corr;
  }
};

EffectTermStream::EffectTermStream(std::vector<EffectTerm> terms, double sample_rate_hz, double offset_nm) : impl_(new Impl) {
  if (!(sample_rate_hz > 0) || !std::isfinite(sample_rate_hz))
    throw std::invalid_argument("effect terms: sample rate must be > 0 Hz");
  impl_->terms = std::move(terms);
  impl_->offset_nm = offset_nm;
  for (const auto& t : impl_->terms) {
    TermConst c;
    c.lag = static_cast<std::size_t>(std::lround(t.lag_s * sample_rate_hz));
    c.alpha = t.time_constant_s > 0 ? std::exp(-1.0 / (t.time_constant_s * sample_rate_hz)) : 0.0;
    c.kind = t.kind();  // throws for an unknown type, naming the known ones
    c.regressors = t.num_regressors();
    c.on_position = t.signal == kSignalPosition;
    c.scales_voltage = t.scales == kSignalVoltage;
    c.in_readings = t.in_readings();
    if (!is_builtin_signal(t.signal)) {
      auto it = std::find(impl_->columns.begin(), impl_->columns.end(), t.signal);
      if (it == impl_->columns.end()) {
        impl_->columns.push_back(t.signal);
        it = impl_->columns.end() - 1;
      }
      c.column = static_cast<int>(it - impl_->columns.begin());
    }
    impl_->consts.push_back(c);
    TermState st;
    st.ring.assign(c.lag, 0.0);
    impl_->states.push_back(st);
    impl_->first.push_back(impl_->k);
    impl_->k += t.num_regressors();
  }
}
EffectTermStream::~EffectTermStream() = default;
EffectTermStream::EffectTermStream(const EffectTermStream& o) : impl_(new Impl(*o.impl_)) {}
EffectTermStream& EffectTermStream::operator=(const EffectTermStream& o) {
  if (this != &o) impl_.reset(new Impl(*o.impl_));
  return *this;
}

const std::vector<std::string>& EffectTermStream::column_signals() const { return impl_->columns; }
std::size_t EffectTermStream::num_regressors() const { return impl_->k; }
const std::vector<EffectTerm>& EffectTermStream::terms() const { return impl_->terms; }
double EffectTermStream::offset_nm() const { return impl_->offset_nm; }
void EffectTermStream::set_offset_nm(double offset_nm) { impl_->offset_nm = offset_nm; }

void EffectTermStream::reset() {
  for (std::size_t i = 0; i < impl_->states.size(); ++i) {
    TermState st;
    st.ring.assign(impl_->consts[i].lag, 0.0);
    impl_->states[i] = st;
  }
}

void EffectTermStream::raw(double v, double x, const double* cols, double* out) const {
  impl_->run(v, x, cols, out, nullptr);
}

void EffectTermStream::standardised(double v, double x, const double* cols, double* out) const {
  raw(v, x, cols, out);
  std::size_t j = 0;
  for (std::size_t i = 0; i < impl_->terms.size(); ++i) {
    const EffectTerm& t = impl_->terms[i];
    const std::size_t k = impl_->consts[i].regressors;
    for (std::size_t r = 0; r < k; ++r, ++j) {
      const double c = r < t.center.size() ? t.center[r] : 0.0;
      const double s = r < t.scale.size() ? t.scale[r] : 1.0;
      out[j] = (out[j] - c) / s;
    }
  }
}

double EffectTermStream::correction(double v, double x, const double* cols, double* readings_nm) const {
  return impl_->run(v, x, cols, nullptr, nullptr, readings_nm);
}

double EffectTermStream::commit(double v, double x, const double* cols, double* readings_nm) {
  // Each term reads only its own state before writing it, so the update can be in place.
  return impl_->run(v, x, cols, nullptr, &impl_->states, readings_nm);
}

void EffectTermStream::raw_and_commit(double v, double x, const double* cols, double* out) {
  impl_->run(v, x, cols, out, &impl_->states);
}

// ---- the model ---------------------------------------------------------------------------------------
std::string AugmentedModel::fixed_rate_reason() const {
  const std::string base = base_->fixed_rate_reason();
  if (!base.empty()) return "its base: " + base;
  for (const EffectTerm& t : terms())
    if (t.lag_s > 0 || t.time_constant_s > 0 || t.type == "rate")
      return "effect term " + t.name() + " counts its lag, low-pass or difference in samples of the training rate";
  return "";
}

void AugmentedModel::set_step_s(double dt_s) {
  if (!runs_at_any_rate()) return check_fixed_step(dt_s);
  base_->set_step_s(dt_s);
}

AugmentedModel::AugmentedModel(ModelPtr base, std::vector<EffectTerm> terms, double offset_nm, double sample_rate_hz)
    : base_(std::move(base)), stream_(std::move(terms), sample_rate_hz, offset_nm), sample_rate_hz_(sample_rate_hz) {
  if (!base_) throw std::invalid_argument("augmented model: no base model");
  if (!std::isfinite(offset_nm)) throw std::invalid_argument("augmented model: offset_nm is not finite");
  meta = base_->meta;
  aux_names_ = base_->aux_inputs();
  n_base_aux_ = aux_names_.size();
  for (const auto& c : stream_.column_signals()) {
    auto it = std::find(aux_names_.begin(), aux_names_.end(), c);
    if (it == aux_names_.end()) {
      aux_names_.push_back(c);
      it = aux_names_.end() - 1;
    }
    col_index_.push_back(static_cast<int>(it - aux_names_.begin()));
  }
}

AugmentedModel::AugmentedModel(const AugmentedModel& o)
    : Model(o),
      base_(o.base_->clone()),
      stream_(o.stream_),
      sample_rate_hz_(o.sample_rate_hz_),
      n_base_aux_(o.n_base_aux_),
      aux_names_(o.aux_names_),
      col_index_(o.col_index_),
      stage_position_(o.stage_position_) {}

void AugmentedModel::split(const ModelInput& in, std::vector<double>& base_aux, std::vector<double>& cols) const {
  base_aux.assign(n_base_aux_, 0.0);
  cols.assign(col_index_.size(), 0.0);
  if (!in.aux) {
    if (!aux_names_.empty()) throw std::invalid_argument("augmented model: inputs " + std::to_string(aux_names_.size()) + " aux values, none given");
    return;
  }
  for (std::size_t i = 0; i < n_base_aux_; ++i) base_aux[i] = in.aux[i];
  for (std::size_t j = 0; j < col_index_.size(); ++j) cols[j] = in.aux[col_index_[j]];
}

namespace {
const Model& base_of(const Model& m) {
  if (const auto* aug = dynamic_cast<const AugmentedModel*>(&m)) return aug->base();
  return m;
}
}  // namespace

bool AugmentedModel::can_adopt_base_state(const Model& running) const {
  const Model& src = base_of(running);
  if (src.kind() != base_->kind() || !src.aux_inputs().empty() || !base_->aux_inputs().empty()) return false;
  YAML::Emitter a, b;
  a << src.to_yaml();
  b << base_->to_yaml();
  return std::string(a.c_str()) == std::string(b.c_str());
}

void AugmentedModel::adopt_base_state(const Model& running, double offset_change_nm) {
  if (!can_adopt_base_state(running) || !std::isfinite(offset_change_nm))
    throw std::invalid_argument("augmented model: the running model's base is not this model's base");
  base_ = base_of(running).clone();
  stream_.set_offset_nm(stream_.offset_nm() + offset_change_nm);
}

void AugmentedModel::reset(double voltage_v, double position_nm) {
  base_->reset(voltage_v, position_nm);
  stream_.reset();
}

double AugmentedModel::base_prediction(const ModelInput& in) const {
  std::vector<double> ba, cols;
  split(in, ba, cols);
  ModelInput bi{in.voltage_v, ba.empty() ? nullptr : ba.data()};
  return base_->predict(bi);
}

double AugmentedModel::predict(const ModelInput& in) const {
  std::vector<double> ba, cols;
  split(in, ba, cols);
  ModelInput bi{in.voltage_v, ba.empty() ? nullptr : ba.data()};
  const double x = base_->predict(bi);
  double readings = 0.0;
  const double corr = stream_.correction(in.voltage_v, x, cols.data(), &readings);
  return x + corr - (stage_position_ ? readings : 0.0);
}

double AugmentedModel::sensor_part_nm(const ModelInput& in) const {
  std::vector<double> ba, cols;
  split(in, ba, cols);
  ModelInput bi{in.voltage_v, ba.empty() ? nullptr : ba.data()};
  double readings = 0.0;
  stream_.correction(in.voltage_v, base_->predict(bi), cols.data(), &readings);
  return readings;
}

bool AugmentedModel::has_sensor_terms() const {
  return std::any_of(stream_.terms().begin(), stream_.terms().end(), [](const EffectTerm& t) { return t.in_readings(); });
}

void AugmentedModel::commit(const ModelInput& in, double position_nm) {
  std::vector<double> ba, cols;
  split(in, ba, cols);
  ModelInput bi{in.voltage_v, ba.empty() ? nullptr : ba.data()};
  const double x = base_->predict(bi);
  double readings = 0.0;
  // the stream reads x, not the base's state
  const double corr = stream_.commit(in.voltage_v, x, cols.data(), &readings) - (stage_position_ ? readings : 0.0);
  base_->commit(bi, position_nm - corr);
  if (base_trace_) base_trace_->push_back(x);
}

std::unique_ptr<Model> AugmentedModel::clone() const { return std::make_unique<AugmentedModel>(*this); }
bool AugmentedModel::uses_position_history() const { return base_->uses_position_history(); }

bool AugmentedModel::is_affine_in_voltage() const {
  if (!base_->is_affine_in_voltage()) return false;
  for (const auto& t : stream_.terms()) {
    // Terms on the voltage or on the (voltage-dependent) base prediction are affine only if linear in it.
    const bool reads_v = t.signal == kSignalVoltage || t.signal == kSignalPosition;
    if (reads_v && t.kind() != TermKind::kLinear) return false;
  }
  return true;
}

std::vector<std::string> AugmentedModel::aux_inputs() const { return aux_names_; }

YAML::Node AugmentedModel::to_yaml() const {
  YAML::Node n;
  n["base_kind"] = base_->kind();
  n["base"] = base_->to_yaml();
  n["sample_rate_hz"] = sample_rate_hz_;
  n["offset_nm"] = stream_.offset_nm();
  n["terms"] = YAML::Node(YAML::NodeType::Sequence);
  for (const auto& t : stream_.terms()) n["terms"].push_back(t.to_yaml());
  return n;
}

std::size_t AugmentedModel::num_parameters() const { return base_->num_parameters() + stream_.num_regressors() + 1; }

ModelPtr AugmentedModel::from_yaml(const YAML::Node& n) {
  if (!n || !n.IsMap()) throw std::runtime_error("augmented model: the model node is not a map");
  for (const char* k : {"base_kind", "base", "sample_rate_hz", "offset_nm", "terms"})
    if (!n[k]) throw std::runtime_error(std::string("augmented model: missing key '") + k + "'");
  for (const auto& kv : n) {
    const std::string k = kv.first.as<std::string>();
    // axis and kind are copied in by the model file reader (model_file.h).
    if (k != "base_kind" && k != "base" && k != "sample_rate_hz" && k != "offset_nm" && k != "terms" && k != "axis" && k != "kind")
      throw std::runtime_error("augmented model: unknown key '" + k + "'");
  }
  const std::string base_kind = n["base_kind"].as<std::string>();
  if (base_kind == "augmented") throw std::runtime_error("augmented model: the base may not itself be augmented");
  if (!n["base"].IsMap()) throw std::runtime_error("augmented model: 'base' is not a map");
  // The base's loader expects what the model file gives every kind: rate, axis and its own kind name.
  YAML::Node base_node = YAML::Clone(n["base"]);
  if (!base_node["sample_rate_hz"]) base_node["sample_rate_hz"] = n["sample_rate_hz"];
  if (!base_node["axis"] && n["axis"]) base_node["axis"] = n["axis"];
  if (!base_node["kind"]) base_node["kind"] = base_kind;
  ModelPtr base = model_kind(base_kind).load(base_node);
  if (n["axis"]) base->meta.axis = n["axis"].as<std::string>();
  base->meta.sample_rate_hz = yaml_num(n, "sample_rate_hz", base->meta.sample_rate_hz);
  std::vector<EffectTerm> terms;
  if (!n["terms"].IsSequence()) throw std::runtime_error("augmented model: 'terms' is not a list");
  for (const auto& t : n["terms"]) terms.push_back(EffectTerm::from_yaml(t));
  const double fs = yaml_num(n, "sample_rate_hz", 0.0);
  const double off = yaml_num(n, "offset_nm", 0.0);
  if (!(fs > 0)) throw std::runtime_error("augmented model: sample_rate_hz must be > 0");
  return std::make_unique<AugmentedModel>(std::move(base), std::move(terms), off, fs);
}

std::vector<double> AugmentedModel::creep_mode_taus_s() const { return base().creep_mode_taus_s(); }

}  // namespace piezo::models
