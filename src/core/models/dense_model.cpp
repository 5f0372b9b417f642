#include "piezo_compensation/models/dense_model.h"

#include <cctype>
#include <cmath>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/linear_model.h"

namespace piezo::models {

namespace {

double leaky(double z, double a) { return z > 0.0 ? z : a * z; }

}  // namespace

DenseNet::DenseNet(const DenseShape& shape) : shape_(shape) {
  if (shape.inputs < 1 || shape.inputs > kMaxWidth) throw std::runtime_error("dense: inputs must be in 1..256");
  if (shape.depth < 0 || shape.depth > 16) throw std::runtime_error("dense: depth must be in 0..16");
  if (shape.width < 1 || shape.width > kMaxWidth) throw std::runtime_error("dense: width must be in 1..256");
  if (!(shape.leaky_slope >= 0.0 && shape.leaky_slope < 1.0))
    throw std::runtime_error("dense: leaky_slope must be in [0, 1)");
  sizes_.push_back(shape.inputs);
  for (int l = 0; l < shape.depth; ++l) sizes_.push_back(shape.width);
  sizes_.push_back(1);
  for (std::size_t l = 1; l < sizes_.size(); ++l)
    num_params_ += static_cast<std::size_t>(sizes_[l] * sizes_[l - 1] + sizes_[l]);
}

Eigen::VectorXd DenseNet::initial_params(std::uint64_t seed) const {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);
  Eigen::VectorXd p = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(num_params_));
  Eigen::Index o = 0;
  for (std::size_t l = 1; l < sizes_.size(); ++l) {
    const double sd = std::sqrt(2.0 / static_cast<double>(sizes_[l - 1]));
    for (int i = 0; i < sizes_[l] * sizes_[l - 1]; ++i) p[o++] = sd * normal(rng);
    o += sizes_[l];  // biases start at zero
  }
  return p;
}

double DenseNet::forward(const double* params, const double* x) const {
  double buf_a[kMaxWidth], buf_b[kMaxWidth];
  const double* in = x;
  double* out = buf_a;
  const double* w = params;
  const std::size_t layers = sizes_.size() - 1;
  for (std::size_t l = 0; l < layers; ++l) {
    const int n_in = sizes_[l], n_out = sizes_[l + 1];
    const double* b = w + n_in * n_out;
    for (int j = 0; j < n_out; ++j) out[j] = b[j];
    for (int i = 0; i < n_in; ++i) {
      const double xi = in[i];
      const double* col = w + i * n_out;
      for (int j = 0; j < n_out; ++j) out[j] += col[j] * xi;
    }
    if (l + 1 < layers)
      for (int j = 0; j < n_out; ++j) out[j] = leaky(out[j], shape_.leaky_slope);
    w = b + n_out;
    in = out;
    out = (out == buf_a) ? buf_b : buf_a;
  }
  return in[0];
}

Eigen::VectorXd DenseNet::forward_batch(const Eigen::VectorXd& params, const Eigen::MatrixXd& x) const {
  Eigen::MatrixXd a = x;
  Eigen::Index o = 0;
  const std::size_t layers = sizes_.size() - 1;
  for (std::size_t l = 0; l < layers; ++l) {
    const int n_in = sizes_[l], n_out = sizes_[l + 1];
    Eigen::Map<const Eigen::MatrixXd> w(params.data() + o, n_out, n_in);
    Eigen::Map<const Eigen::VectorXd> b(params.data() + o + n_in * n_out, n_out);
    o += n_in * n_out + n_out;
    Eigen::MatrixXd z = w * a;
    z.colwise() += b;
    if (l + 1 < layers) z = z.unaryExpr([s = shape_.leaky_slope](double v) { return leaky(v, s); });
    a = std::move(z);
  }
  return a.row(0).transpose();
}

double DenseNet::loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x, const Eigen::VectorXd& y,
                           Eigen::VectorXd* grad) const {
  const std::size_t layers = sizes_.size() - 1;
  std::vector<Eigen::MatrixXd> acts(layers + 1), pre(layers);
  std::vector<Eigen::Index> offs(layers);
  acts[0] = x;
  Eigen::Index o = 0;
  for (std::size_t l = 0; l < layers; ++l) {
    const int n_in = sizes_[l], n_out = sizes_[l + 1];
    offs[l] = o;
    Eigen::Map<const Eigen::MatrixXd> w(params.data() + o, n_out, n_in);
    Eigen::Map<const Eigen::VectorXd> b(params.data() + o + n_in * n_out, n_out);
    o += n_in * n_out + n_out;
    pre[l].noalias() = w * acts[l];
    pre[l].colwise() += b;
    if (l + 1 < layers)
      acts[l + 1] = pre[l].unaryExpr([s = shape_.leaky_slope](double v) { return leaky(v, s); });
    else
      acts[l + 1] = pre[l];
  }
  const Eigen::RowVectorXd err = acts[layers].row(0) - y.transpose();
  const double loss = err.squaredNorm();
  if (!grad) return loss;
  Eigen::MatrixXd delta = 2.0 * err;  // d loss / d pre of the output layer (1 × n)
  for (std::size_t l = layers; l-- > 0;) {
    const int n_in = sizes_[l], n_out = sizes_[l + 1];
    Eigen::Map<Eigen::MatrixXd> gw(grad->data() + offs[l], n_out, n_in);
    Eigen::Map<Eigen::VectorXd> gb(grad->data() + offs[l] + n_in * n_out, n_out);
    gw.noalias() += delta * acts[l].transpose();
    gb += delta.rowwise().sum();
    if (l > 0) {
      Eigen::Map<const Eigen::MatrixXd> w(params.data() + offs[l], n_out, n_in);
      Eigen::MatrixXd up = w.transpose() * delta;
      const double s = shape_.leaky_slope;
      delta = up.array() * pre[l - 1].unaryExpr([s](double v) { return v > 0.0 ? 1.0 : s; }).array();
    }
  }
  return loss;
}

// ---- model --------------------------------------------------------------------------------------------------

DenseModel::DenseModel(const features::FeatureSpec& spec, double sample_rate_hz, const DenseShape& shape,
                       Eigen::VectorXd params, TargetScale target)
    : stream_(spec, sample_rate_hz), sample_rate_hz_(sample_rate_hz), net_(shape), params_(std::move(params)),
      target_(target) {
  if (static_cast<int>(spec.size()) != shape.inputs)
    throw std::runtime_error("dense: the feature spec has " + std::to_string(spec.size()) +
                             " features but the network expects " + std::to_string(shape.inputs));
  if (static_cast<std::size_t>(params_.size()) != net_.num_params())
    throw std::runtime_error("dense: weight count does not match the architecture");
  meta.sample_rate_hz = sample_rate_hz;
}

double DenseModel::predict(const ModelInput& in) const {
  double x[DenseNet::kMaxWidth];
  stream_.compute(in, x);
  return target_.to_nm(net_.forward(params_.data(), x));
}

YAML::Node DenseModel::to_yaml() const {
  YAML::Node n;
  n["sample_rate_hz"] = sample_rate_hz_;
  n["features"] = stream_.spec().to_yaml();
  n["target"] = target_.to_yaml();
  n["hyperparameters"]["depth"] = net_.shape().depth;
  n["hyperparameters"]["width"] = net_.shape().width;
  n["hyperparameters"]["leaky_slope"] = net_.shape().leaky_slope;
  if (training_info) n["training"] = training_info;
  n["weights"] = yaml_list(params_);
  return n;
}

std::unique_ptr<DenseModel> DenseModel::from_yaml(const YAML::Node& node) {
  const NeuralFileHeader header = read_neural_file_header(node, "dense", {"depth", "width", "leaky_slope"});
  const YAML::Node h = header.hyperparameters;
  DenseShape shape;
  shape.inputs = static_cast<int>(header.spec.size());
  shape.depth = yaml_int(h, "depth", 0, 16, "model.hyperparameters");
  shape.width = yaml_int(h, "width", 1, 256, "model.hyperparameters");
  shape.leaky_slope = yaml_number(h, "leaky_slope", "model.hyperparameters");
  const DenseNet net(shape);
  const std::vector<double> w = yaml_numbers(node, "weights", static_cast<long>(net.num_params()));
  auto m = std::make_unique<DenseModel>(header.spec, header.sample_rate_hz, shape, Eigen::Map<const Eigen::VectorXd>(w.data(), static_cast<Eigen::Index>(w.size())), header.target);
  if (node["training"]) m->training_info = node["training"];
  return m;
}

std::string DenseModel::export_c99_network(const std::string& prefix) const {
  std::ostringstream os;
  os << std::setprecision(17);
  const DenseShape& s = net_.shape();
  os << "/* Dense network (" << s.depth << " x " << s.width << ", leaky ReLU " << s.leaky_slope
     << "): position [nm] from the standardised feature vector. Generated by piezo_compensation. */\n"
     << "#define " << prefix << "_NUM_FEATURES " << s.inputs << "\n"
     << "static const double " << prefix << "_weights[" << net_.num_params() << "] = {";
  for (Eigen::Index i = 0; i < params_.size(); ++i) os << (i ? "," : "") << (i % 4 == 0 ? "\n  " : " ") << params_[i];
  os << "\n};\n"
     << "static double " << prefix << "_network(const double* x) {\n"
     << "  double a[" << DenseNet::kMaxWidth << "], b[" << DenseNet::kMaxWidth << "];\n"
     << "  const double* in = x; double* out = a; const double* w = " << prefix << "_weights;\n"
     << "  static const int sizes[] = {" << s.inputs;
  for (int l = 0; l < s.depth; ++l) os << ", " << s.width;
  os << ", 1};\n"
     << "  int l, i, j;\n"
     << "  for (l = 0; l < " << s.depth + 1 << "; ++l) {\n"
     << "    const int n_in = sizes[l], n_out = sizes[l + 1];\n"
     << "    const double* bias = w + n_in * n_out;\n"
     << "    for (j = 0; j < n_out; ++j) out[j] = bias[j];\n"
     << "    for (i = 0; i < n_in; ++i) for (j = 0; j < n_out; ++j) out[j] += w[i * n_out + j] * in[i];\n"
     << "    if (l < " << s.depth << ") for (j = 0; j < n_out; ++j) if (out[j] < 0.0) out[j] *= " << s.leaky_slope << ";\n"
     << "    w = bias + n_out; in = out; out = (out == a) ? b : a;\n"
     << "  }\n"
     << "  return " << target_.c99_expression("in[0]") << ";\n"
     << "}\n";
  return os.str();
}

std::string DenseModel::export_c99(const std::string& prefix) const {
  return neural_c99_header(stream_.spec(), sample_rate_hz_, prefix, export_c99_network(prefix));
}

std::string neural_c99_header(const features::FeatureSpec& spec, double sample_rate_hz, const std::string& prefix,
                              const std::string& network_code) {
  const std::string feat = prefix + "_feat";
  // Zero weights: only the linear exporter's feature engine (state, init, feature, commit) is used.
  const LinearModel engine(spec, sample_rate_hz, Eigen::VectorXd::Zero(static_cast<Eigen::Index>(spec.size())), 0.0);
  std::string text = export_c99_linear(engine, feat);
  // Drop the engine's own predict/step/inverse: unused static functions break -Werror builds.
  for (const std::string name : {"_predict(", "_step(", "_inverse("}) {
    const std::size_t at = text.find("static double " + feat + name);
    if (at == std::string::npos) continue;
    const std::size_t end = text.find("\n}\n", at);
    if (end == std::string::npos) throw std::runtime_error("C export: unexpected feature engine layout");
    text.erase(at, end + 3 - at);
  }
  const std::string has_inverse = "#define " + feat + "_HAS_INVERSE 1\n";
  for (std::size_t at; (at = text.find(has_inverse)) != std::string::npos;) text.erase(at, has_inverse.size());
  std::string guard = prefix + "_NET_H_";
  for (auto& c : guard) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  std::ostringstream os;
  os << text << "\n#ifndef " << guard << "\n#define " << guard << "\n\n" << network_code << "\n"
     << "typedef " << feat << "_state " << prefix << "_state;\n"
     << "static void " << prefix << "_init(" << prefix << "_state* st, double voltage_v, double position_nm) {\n"
     << "  " << feat << "_init(st, voltage_v, position_nm);\n}\n"
     << "static double " << prefix << "_predict(const " << prefix << "_state* st, double voltage_v) {\n"
     << "  double z[" << spec.size() << "];\n  int i;\n"
     << "  for (i = 0; i < " << spec.size() << "; ++i) z[i] = (" << feat << "_feature(st, i, voltage_v) - " << feat
     << "_mean[i]) / " << feat << "_scale[i];\n"
     << "  return " << prefix << "_network(z);\n}\n"
     << "static void " << prefix << "_commit(" << prefix << "_state* st, double voltage_v, double position_nm) {\n"
     << "  " << feat << "_commit(st, voltage_v, position_nm);\n}\n"
     << "/* predict + commit; measured_nm = NAN remembers the prediction (free-run). */\n"
     << "static double " << prefix << "_step(" << prefix << "_state* st, double voltage_v, double measured_nm) {\n"
     << "  const double y = " << prefix << "_predict(st, voltage_v);\n"
     << "  " << prefix << "_commit(st, voltage_v, isnan(measured_nm) ? y : measured_nm);\n"
     << "  return y;\n}\n\n#endif\n";
  return os.str();
}

}  // namespace piezo::models
