#include "piezo_compensation/models/model_file.h"

#include <cmath>
#include <fstream>
#include <sstream>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/util/fingerprint.h"

namespace piezo::models {

namespace {
// training.state_prior: one {intercept_nm, slope_nm_per_v, sigma_nm} per linear state of the model.
std::vector<LinearStatePrior> read_state_prior(const YAML::Node& n, std::size_t states) {
  const std::string key = "training.state_prior";
  if (!n.IsSequence()) throw std::runtime_error(key + ": expected a list");
  if (n.size() != states)
    throw std::runtime_error(key + ": " + std::to_string(n.size()) + " entries for a model with " +
                             std::to_string(states) + " linear (creep) states");
  std::vector<LinearStatePrior> out;
  for (std::size_t k = 0; k < n.size(); ++k) {
    const std::string at = key + "[" + std::to_string(k) + "]";
    if (!n[k].IsMap()) throw std::runtime_error(at + ": expected a mapping");
    double x[3] = {NAN, NAN, NAN};
    const char* names[3] = {"intercept_nm", "slope_nm_per_v", "sigma_nm"};
    for (int f = 0; f < 3; ++f) {
      try {
        x[f] = n[k][names[f]].as<double>();
      } catch (const YAML::Exception&) {
      }
      if (!std::isfinite(x[f]) || (f == 2 && x[f] < 0))
        throw std::runtime_error(at + "." + names[f] + ": expected a finite number" + (f == 2 ? " >= 0" : ""));
    }
    out.push_back({x[0], x[1], x[2]});
  }
  return out;
}
}  // namespace

YAML::Node model_to_file_yaml(const Model& m) {
  YAML::Node root;
  root["format_version"] = kModelFormatVersion;
  root["kind"] = m.kind();
  root["axis"] = m.meta.axis;
  root["sample_rate_hz"] = m.meta.sample_rate_hz;
  root["created_utc"] = m.meta.created_utc;
  root["training"]["fingerprint"] = m.meta.training_fingerprint;
  root["training"]["source"] = m.meta.training_source;
  for (const TrainingSpan& t : m.meta.trained_on) {
    YAML::Node n;
    n["source"] = t.source;
    n["begin_s"] = t.begin_s;
    n["end_s"] = t.end_s;
    n["rows"] = t.rows;
    n["fingerprint"] = t.fingerprint;
    root["training"]["recordings"].push_back(n);
  }
  if (!m.meta.fitted_on.empty()) root["training"]["fitted_on"] = m.meta.fitted_on;
  if (!m.meta.time_clock.empty()) root["training"]["time_clock"] = m.meta.time_clock;
  if (std::isfinite(m.meta.train_voltage_min_v) && std::isfinite(m.meta.train_voltage_max_v)) {
    root["training"]["voltage_min_v"] = m.meta.train_voltage_min_v;
    root["training"]["voltage_max_v"] = m.meta.train_voltage_max_v;
  }
  for (const LinearStatePrior& p : m.meta.state_prior) {
    YAML::Node n;
    n["intercept_nm"] = p.intercept_nm;
    n["slope_nm_per_v"] = p.slope_nm_per_v;
    n["sigma_nm"] = p.sigma_nm;
    root["training"]["state_prior"].push_back(n);
  }
  YAML::Node val(YAML::NodeType::Map);
  for (const auto& [k, v] : m.meta.validation) val[k] = v;
  root["validation"] = val;
  if (m.meta.selection && !m.meta.selection.IsNull()) root["selection"] = m.meta.selection;
  if (m.meta.estimator && !m.meta.estimator.IsNull()) root["estimator"] = m.meta.estimator;
  root["num_parameters"] = static_cast<unsigned long>(m.num_parameters());
  root["model"] = m.to_yaml();
  return root;
}

namespace {
std::runtime_error key_error(const std::string& key, const std::string& what) {
  return std::runtime_error(key + ": " + what);
}

// The `training:` block of a model file into the model's metadata (models/model.h, ModelMeta).
void read_training_meta(const YAML::Node& t, Model& m) {
  if (!t.IsMap()) throw key_error("training", "expected a mapping");
  if (t["fingerprint"]) m.meta.training_fingerprint = t["fingerprint"].as<std::string>();
  if (t["source"]) m.meta.training_source = t["source"].as<std::string>();
  if (const YAML::Node rs = t["recordings"]) {
    if (!rs.IsSequence()) throw key_error("training.recordings", "expected a list");
    for (const auto& r : rs) {
      TrainingSpan sp;
      try {
        sp.source = r["source"].as<std::string>();
        sp.begin_s = r["begin_s"].as<double>();
        sp.end_s = r["end_s"].as<double>();
        sp.rows = r["rows"].as<std::size_t>();
        sp.fingerprint = r["fingerprint"].as<std::string>();
      } catch (const YAML::Exception&) {
        throw key_error("training.recordings", "each entry needs source, begin_s, end_s, rows and fingerprint");
      }
      m.meta.trained_on.push_back(sp);
    }
  }
  if (const YAML::Node f = t["fitted_on"]) {
    const std::string on = f.IsScalar() ? f.Scalar() : std::string();
    if (on != kFittedOnSimulated && on != kFittedOnRecorded)
      throw key_error("training.fitted_on", "expected simulated or recorded");
    m.meta.fitted_on = on;
  }
  if (t["time_clock"]) m.meta.time_clock = t["time_clock"].as<std::string>();
  if (t["voltage_min_v"] || t["voltage_max_v"]) {
    double lo = NAN, hi = NAN;
    try {
      lo = t["voltage_min_v"].as<double>();
      hi = t["voltage_max_v"].as<double>();
    } catch (const YAML::Exception&) {
    }
    if (!(std::isfinite(lo) && std::isfinite(hi) && lo <= hi))
      throw key_error("training.voltage_min_v/voltage_max_v", "expected two finite numbers, min <= max");
    m.meta.train_voltage_min_v = lo;
    m.meta.train_voltage_max_v = hi;
  }
  if (t["state_prior"]) m.meta.state_prior = read_state_prior(t["state_prior"], m.linear_state_count());
}

}  // namespace

ModelPtr model_from_file_yaml(const YAML::Node& root, const std::string& where) {
  try {
    if (!root || !root.IsMap()) throw std::runtime_error("expected a YAML mapping at the top level");
    if (!root["format_version"]) throw key_error("format_version", "missing key");
    int version = 0;
    try {
      version = root["format_version"].as<int>();
    } catch (const YAML::Exception&) {
      throw key_error("format_version", "expected an integer");
    }
    if (version > kModelFormatVersion)
      throw key_error("format_version", std::to_string(version) + " is newer than this program reads (" +
                                          std::to_string(kModelFormatVersion) + "); update piezo_compensation");
    if (version < 1) throw key_error("format_version", "must be >= 1");
    for (const char* k : {"kind", "axis", "sample_rate_hz", "model"})
      if (!root[k]) throw key_error(k, "missing key");
    if (!root["kind"].IsScalar()) throw key_error("kind", "expected a string");
    if (!root["axis"].IsScalar()) throw key_error("axis", "expected a string");
    const std::string kind = root["kind"].Scalar();
    const std::string axis = root["axis"].Scalar();
    if (io::axis_index_or_none(axis) < 0) throw key_error("axis", "expected one of " + io::axis_names_list() + ", got '" + axis + "'");
    double rate = 0;
    try {
      rate = root["sample_rate_hz"].as<double>();
    } catch (const YAML::Exception&) {
      throw key_error("sample_rate_hz", "expected a number");
    }
    // Kinds size buffers and time constants from the rate: bounded so a file cannot ask for gigabytes.
    if (!(rate > 0) || !(rate <= 1e6)) throw key_error("sample_rate_hz", "must be in (0, 1e6] Hz");
    if (!root["model"].IsMap()) throw key_error("model", "expected a mapping");
    const ModelKind& mk = model_kind(kind);  // throws listing known kinds
    if (!mk.load) throw key_error("kind", "'" + kind + "' cannot be loaded");
    YAML::Node node = YAML::Clone(root["model"]);
    if (!node["sample_rate_hz"]) node["sample_rate_hz"] = rate;
    if (!node["axis"]) node["axis"] = axis;
    if (!node["kind"]) node["kind"] = kind;
    ModelPtr m = mk.load(node);
    if (!m) throw std::runtime_error("kind '" + kind + "' loader returned nothing");
    if (m->kind() != kind) throw key_error("kind", "'" + kind + "' but the model node describes '" + m->kind() + "'");
    m->meta.axis = axis;
    m->meta.sample_rate_hz = rate;
    if (root["created_utc"] && root["created_utc"].IsScalar()) m->meta.created_utc = root["created_utc"].Scalar();
    if (const YAML::Node t = root["training"]) read_training_meta(t, *m);
    if (const YAML::Node v = root["validation"]) {
      if (!v.IsMap()) throw key_error("validation", "expected a mapping");
      for (const auto& kv : v) {
        try {
          m->meta.validation[kv.first.as<std::string>()] = kv.second.as<double>();
        } catch (const YAML::Exception&) {
          throw key_error("validation." + kv.first.as<std::string>(), "expected a number");
        }
      }
    }
    if (const YAML::Node s = root["selection"]) {
      if (!s.IsMap()) throw key_error("selection", "expected a mapping");
      m->meta.selection = YAML::Clone(s);
    }
    if (const YAML::Node s = root["estimator"]) {  // checked field by field where it is used (estimation/)
      if (!s.IsMap()) throw key_error("estimator", "expected a mapping");
      m->meta.estimator = YAML::Clone(s);
    }
    return m;
  } catch (const ModelFileError&) {
    throw;
  } catch (const std::exception& e) {
    throw ModelFileError(where + ": " + e.what());
  }
}

void save_model(const std::string& path, const Model& model) {
  YAML::Emitter out;
  out.SetDoublePrecision(17);
  out << model_to_file_yaml(model);
  std::ofstream f(path);
  if (!f) throw ModelFileError(path + ": cannot open for writing");
  f << "# piezo_compensation model file (docs/models.md)\n" << out.c_str() << "\n";
  if (!f) throw ModelFileError(path + ": write failed");
}

ModelPtr load_model(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::BadFile&) {
    throw ModelFileError(path + ": cannot open");
  } catch (const YAML::Exception& e) {
    throw ModelFileError(path + ": not valid YAML: " + e.what());
  }
  return model_from_file_yaml(root, path);
}

void check_model_axis(const Model& m, const std::string& axis, const std::string& where) {
  if (m.meta.axis != axis)
    throw ModelFileError(where + ": model fitted for axis " + m.meta.axis + ", loaded for axis " + axis +
                         ": refused (one model per axis; fit one on axis " + axis + "'s recording)");
}

namespace {
std::string span_hash(const io::AxisSeries& ax, std::size_t b, std::size_t e) {
  std::uint64_t h = util::fnv1a64(ax.voltage_v.data() + b, (e - b) * sizeof(double));
  h = util::fnv1a64(ax.position_nm.data() + b, (e - b) * sizeof(double), h);
  std::ostringstream os;
  os << std::hex << h;
  return os.str();
}
}  // namespace

std::vector<TrainingSpan> training_spans(const io::Dataset& data, const std::string& axis) {
  std::vector<TrainingSpan> out;
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [b, e] = data.recording_rows(k);
    if (e <= b) continue;
    const double shift = data.recordings.empty() ? 0.0 : data.recordings[k].time_shift_s;
    TrainingSpan s;
    s.source = data.recordings.empty() ? data.source_or_data() : data.recordings[k].name;
    s.begin_s = data.time_s[b] - shift;
    s.end_s = data.time_s[e - 1] - shift;
    s.rows = e - b;
    s.fingerprint = span_hash(data.axis(axis), b, e);
    out.push_back(s);
  }
  return out;
}

std::string training_overlap(const ModelMeta& meta, const io::Dataset& data, const std::string& axis,
                             const std::string& model_path) {
  if (!data.has_axis(axis)) return "";
  const io::AxisSeries& ax = data.axis(axis);
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    const double shift = data.recordings.empty() ? 0.0 : data.recordings[k].time_shift_s;
    for (const TrainingSpan& sp : meta.trained_on) {
      const double tol = 1e-6 * std::max(1.0, std::abs(sp.end_s));
      std::size_t b = rb;
      while (b < re && data.time_s[b] - shift < sp.begin_s - tol) ++b;
      if (b == re || data.time_s[b] - shift > sp.begin_s + tol || b + sp.rows > re) continue;
      if (std::abs(data.time_s[b + sp.rows - 1] - shift - sp.end_s) > tol) continue;
      if (span_hash(ax, b, b + sp.rows) != sp.fingerprint) continue;
      std::ostringstream os;
      const std::string name = data.recordings.empty() ? data.source_or_data() : data.recordings[k].name;
      os << name << ": rows " << b - rb + 2 << "-" << b - rb + sp.rows + 1 << " (t = " << sp.begin_s << "-" << sp.end_s
         << " s) are rows " << model_path << " was trained on (" << sp.source << ")";
      return os.str();
    }
  }
  return "";
}

void check_model_matches_data(const Model& m, const io::Dataset& data, const std::string& where,
                              const std::string& axis_in) {
  const std::string& axis = axis_in.empty() ? m.meta.axis : axis_in;
  if (!data.has_axis(axis))
    throw ModelFileError(where + ": model is for axis '" + axis + "' but " +
                         (data.source.empty() ? std::string("the data") : data.source) + " has no such axis");
  const double rate = data.sample_rate_hz();
  if (!m.runs_at_any_rate() && std::abs(rate - m.meta.sample_rate_hz) > Model::kStepTolerance * m.meta.sample_rate_hz) {
    std::ostringstream os;
    os << where << ": sample_rate_hz " << m.meta.sample_rate_hz << " Hz does not match the data's " << rate << " Hz ("
       << data.source_or_data() << "): " << m.fixed_rate_reason();
    throw ModelFileError(os.str());
  }
  // Inputs as every tool streams them (model_stream.h's one resolver): time_s, aux columns and the other axes'
  // voltage or position, which are axis columns and never aux ones.
  try {
    InputResolver(data, m.aux_inputs(), axis);
  } catch (const io::DataError& e) {
    throw ModelFileError(where + ": " + e.what());
  }
}

}  // namespace piezo::models
