#include "piezo_compensation/training/fit_common.h"

#include <algorithm>
#include <cmath>
#include <ctime>
#include <stdexcept>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/training/lasso.h"
#include "piezo_compensation/util/fingerprint.h"

namespace piezo::training {

void for_each_sample(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                     const std::function<void(std::size_t, const double*, double)>& fn, std::size_t begin,
                     std::size_t end) {
  end = std::min(end, data.size());
  if (begin >= end) return;
  const io::AxisSeries& ax = data.axis(axis);
  features::FeatureStream fs(spec, data.sample_rate_hz());
  AuxRows aux(data, spec.aux_signals(), axis);
  std::vector<double> x(fs.size());
  fs.reset(ax.voltage_v[begin], ax.position_nm[begin]);
  for (std::size_t i = begin; i < end; ++i) {
    if (i > begin && data.starts_recording(i)) fs.reset(ax.voltage_v[i], ax.position_nm[i]);  // its own history
    features::ModelInput in{ax.voltage_v[i], aux.at(i)};
    fs.compute(in, x.data());
    fn(i, x.data(), ax.position_nm[i]);
    fs.commit(in, ax.position_nm[i]);
  }
}

features::FeatureSpec fit_standardisation(features::FeatureSpec spec, const io::Dataset& data, const std::string& axis) {
  spec.mean.clear();
  spec.scale.clear();
  const std::size_t p = spec.size();
  // Shifted sums (first sample as origin) keep the variance accurate for large offsets.
  std::vector<double> origin(p, 0.0), s(p, 0.0), ss(p, 0.0);
  double n = 0;
  bool first = true;
  for_each_sample(spec, data, axis, [&](std::size_t, const double* x, double) {
    if (first) {
      std::copy(x, x + p, origin.begin());
      first = false;
    }
    for (std::size_t j = 0; j < p; ++j) {
      const double d = x[j] - origin[j];
      s[j] += d;
      ss[j] += d * d;
    }
    n += 1;
  });
  if (n < 2) throw std::runtime_error("standardisation: need at least 2 samples, got " + std::to_string(int(n)));
  spec.mean.resize(p);
  spec.scale.resize(p);
  for (std::size_t j = 0; j < p; ++j) {
    const double m = s[j] / n;
    const double var = std::max(0.0, ss[j] / n - m * m);
    spec.mean[j] = origin[j] + m;
    const double sd = std::sqrt(var);
    spec.scale[j] = sd > 1e-12 * (1 + std::abs(spec.mean[j])) ? sd : 1.0;
  }
  return spec;
}

GramStats::GramStats(std::size_t p) : sx(Eigen::VectorXd::Zero(p)), sxy(Eigen::VectorXd::Zero(p)), sxx(Eigen::MatrixXd::Zero(p, p)) {}

GramStats& GramStats::operator+=(const GramStats& o) {
  n += o.n;
  sy += o.sy;
  syy += o.syy;
  sx += o.sx;
  sxy += o.sxy;
  sxx += o.sxx;
  return *this;
}
GramStats& GramStats::operator-=(const GramStats& o) {
  n -= o.n;
  sy -= o.sy;
  syy -= o.syy;
  sx -= o.sx;
  sxy -= o.sxy;
  sxx -= o.sxx;
  return *this;
}

double GramStats::sse(const Eigen::VectorXd& beta, double b) const {
  return syy - 2 * b * sy - 2 * beta.dot(sxy) + n * b * b + 2 * b * beta.dot(sx) + beta.dot(sxx * beta);
}

std::vector<GramStats> block_gram(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                                  int blocks, const ProgressFn& progress) {
  if (blocks < 1) throw std::runtime_error("block_gram: need at least one block");
  const std::size_t p = spec.size(), N = data.size();
  if (N < static_cast<std::size_t>(blocks) * 2)
    throw std::runtime_error("block_gram: " + std::to_string(N) + " samples are too few for " + std::to_string(blocks) +
                             " blocks");
  std::vector<GramStats> out(blocks, GramStats(p));
  constexpr std::size_t kChunk = 4096;
  Eigen::MatrixXd X(kChunk, p);
  Eigen::VectorXd y(kChunk);
  std::size_t fill = 0;
  int cur = 0;
  auto flush = [&]() {
    if (!fill) return;
    GramStats& g = out[cur];
    auto Xc = X.topRows(fill);
    auto yc = y.head(fill);
    g.n += static_cast<double>(fill);
    g.sy += yc.sum();
    g.syy += yc.squaredNorm();
    g.sx += Xc.colwise().sum().transpose();
    g.sxy.noalias() += Xc.transpose() * yc;
    g.sxx.selfadjointView<Eigen::Lower>().rankUpdate(Xc.transpose());
    fill = 0;
  };
  for_each_sample(spec, data, axis, [&](std::size_t i, const double* x, double target) {
    const int b = static_cast<int>(i * static_cast<std::size_t>(blocks) / N);
    if (b != cur) {
      flush();
      cur = b;
    }
    for (std::size_t j = 0; j < p; ++j) X(fill, j) = x[j];
    y(fill) = target;
    if (++fill == kChunk) flush();
    if (progress && i % (1 << 16) == 0) progress(double(i), double(N), "features");
  });
  flush();
  for (auto& g : out) g.sxx = g.sxx.selfadjointView<Eigen::Lower>();  // fill the upper half
  if (progress) progress(double(N), double(N), "features");
  return out;
}

Design build_design(const features::FeatureSpec& spec, const io::Dataset& data, const std::string& axis,
                    std::size_t stride) {
  stride = std::max<std::size_t>(1, stride);
  const std::size_t rows = (data.size() + stride - 1) / stride;
  Design d;
  d.X.resize(rows, spec.size());
  d.y.resize(rows);
  std::size_t r = 0;
  for_each_sample(spec, data, axis, [&](std::size_t i, const double* x, double target) {
    if (i % stride) return;
    for (std::size_t j = 0; j < spec.size(); ++j) d.X(r, j) = x[j];
    d.y(r++) = target;
  });
  d.X.conservativeResize(r, Eigen::NoChange);
  d.y.conservativeResize(r);
  return d;
}

Eigen::VectorXd solve_normal(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, double ridge) {
  const Eigen::Index p = G.rows();
  if (p == 0) return Eigen::VectorXd();
  Eigen::MatrixXd A = G;
  A.diagonal().array() += ridge;
  Eigen::LDLT<Eigen::MatrixXd> ldlt(A);
  if (ldlt.info() == Eigen::Success && ldlt.isPositive()) {
    Eigen::VectorXd x = ldlt.solve(c);
    if (x.allFinite() && (A * x - c).norm() <= 1e-6 * (1 + c.norm())) return x;
  }
  return A.completeOrthogonalDecomposition().solve(c);
}

features::FeatureSpec resolve_features(const FitRequest& req, const std::string& default_set) {
  if (!req.train) throw std::runtime_error("fit: no training data");
  const features::DataSpan span = io::data_span(*req.train, req.axis);
  const YAML::Node f = req.options ? req.options["features"] : YAML::Node();
  features::FeatureSpec spec;
  const std::string name = !f ? default_set : f.IsScalar() ? (f.as<std::string>().empty() ? default_set : f.as<std::string>()) : "";
  if (name == "lasso" || name == "voltage_lasso") {
    // The lasso's survivors (λ_1se) among the candidates placed on the data; voltage_lasso: among those that read no
    // position (a free run then needs no fed-back prediction).
    const auto run = [&] {
      features::FeatureSpec cands = features::candidate_features(&span);
      if (name == "voltage_lasso") cands = features::voltage_only(std::move(cands));
      return lasso_survivors(cands, *req.train, req.axis, req.progress);
    };
    spec = req.lasso_cache ? req.lasso_cache->get(name + "|" + req.axis + "|" + util::fingerprint(*req.train), run)
                           : run();
    if (spec.size() == 0)
      throw std::runtime_error("features (" + name + "): the lasso kept no candidate feature at λ_1se: the measured "
                               "position of axis " + req.axis + " does not follow the voltage in the training data "
                               "(a disconnected sensor, or no motion?); a fixed set fits anyway (features=voltage_history)");
  } else if (!name.empty()) {
    spec = features::named_features(name, &span);
  } else if (f.IsMap()) {
    spec = features::FeatureSpec::from_yaml(f);
  } else {
    throw std::runtime_error("option 'features': expected a set name (study, candidates, physics, voltage_history, lasso, voltage_lasso) or a spec");
  }
  if (spec.size() == 0) throw std::runtime_error("option 'features': the feature set is empty");
  return fit_standardisation(spec, *req.train, req.axis);
}

features::FeatureSpec LassoFeatureCache::get(const std::string& key,
                                             const std::function<features::FeatureSpec()>& resolve) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = specs_.find(key);
  if (it != specs_.end()) return it->second;
  ++runs_;
  return specs_.emplace(key, resolve()).first->second;
}

std::string utc_now_iso8601() {
  std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

models::ModelMeta make_meta(const FitRequest& req) {
  models::ModelMeta m;
  m.axis = req.axis;
  m.sample_rate_hz = req.train->sample_rate_hz();
  m.training_fingerprint = util::fingerprint(*req.train);
  m.training_source = req.train->source;
  m.created_utc = utc_now_iso8601();
  const io::DataSpan span = io::data_span(*req.train, req.axis);
  m.train_voltage_min_v = span.voltage_min_v;
  m.train_voltage_max_v = span.voltage_max_v;
  return m;
}

double option_num(const YAML::Node& o, const std::string& key, double def) {
  if (!o || !o[key]) return def;
  try {
    const double v = o[key].as<double>();
    if (!std::isfinite(v)) throw std::runtime_error("");
    return v;
  } catch (const std::exception&) {
    throw std::runtime_error("option '" + key + "': expected a finite number");
  }
}
int option_int(const YAML::Node& o, const std::string& key, int def) {
  if (!o || !o[key]) return def;
  try {
    return o[key].as<int>();
  } catch (const std::exception&) {
    throw std::runtime_error("option '" + key + "': expected an integer");
  }
}
bool option_bool(const YAML::Node& o, const std::string& key, bool def) {
  const std::string v = option_str(o, key, def ? "true" : "false");
  if (v != "true" && v != "false") throw std::runtime_error("option '" + key + "': expected true or false, got '" + v + "'");
  return v == "true";
}
std::string option_str(const YAML::Node& o, const std::string& key, const std::string& def) {
  if (!o || !o[key]) return def;
  if (!o[key].IsScalar()) throw std::runtime_error("option '" + key + "': expected a string");
  return o[key].as<std::string>();
}

ColumnLinearFit linear_fit_columns(const Eigen::MatrixXd& x, const Eigen::VectorXd& y) {
  const Eigen::Index n = x.cols();
  const Eigen::VectorXd mx = x.rowwise().mean();
  const Eigen::MatrixXd xc = x.colwise() - mx;
  const Eigen::MatrixXd g = xc * xc.transpose() / static_cast<double>(n);
  const Eigen::VectorXd c = xc * (y.array() - y.mean()).matrix() / static_cast<double>(n);
  ColumnLinearFit f;
  f.beta = solve_normal(g, c, 1e-6);
  f.intercept = y.mean() - f.beta.dot(mx);
  return f;
}

bool neural_linear_init(const YAML::Node& options) {
  const std::string init = option_str(options, "init", "linear");
  if (init != "linear" && init != "random")
    throw std::runtime_error("option 'init': expected linear (start at the least-squares fit of the features) or "
                             "random, got '" + init + "'");
  return init == "linear";
}

bool validation_prefers(const std::vector<double>& a, const std::vector<double>& b, std::size_t block) {
  const std::size_t n = std::min(a.size(), b.size()), k = block ? n / block : 0;
  if (k < 4) {
    double d = 0.0;
    for (std::size_t t = 0; t < n; ++t) d += a[t] - b[t];
    return d < 0.0;
  }
  std::vector<double> m(k, 0.0);
  for (std::size_t t = 0; t < k * block; ++t) m[t / block] += (a[t] - b[t]) / double(block);
  double mean = 0, var = 0;
  for (double x : m) mean += x / double(k);
  for (double x : m) var += (x - mean) * (x - mean) / double(k - 1);
  return mean < -2.0 * std::sqrt(var / double(k));
}

}  // namespace piezo::training
