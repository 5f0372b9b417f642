#include "piezo_compensation/models/lstm_model.h"

#include <cmath>
#include <random>
#include <stdexcept>

#include "piezo_compensation/models/activations.h"

namespace piezo::models {

LstmNet::LstmNet(const LstmShape& shape) : shape_(shape) {
  if (shape.inputs < 1 || shape.inputs > 256) throw std::runtime_error("lstm: inputs must be in 1..256");
  if (shape.layers < 1 || shape.layers > kMaxLayers) throw std::runtime_error("lstm: layers must be in 1..8");
  if (shape.hidden < 1 || shape.hidden > kMaxHidden) throw std::runtime_error("lstm: hidden must be in 1..256");
  Eigen::Index o = 0;
  const Eigen::Index H = shape.hidden;
  for (int l = 0; l < shape.layers; ++l) {
    layer_offset_.push_back(o);
    o += 4 * H * layer_inputs(l) + 4 * H * H + 4 * H;
  }
  head_offset_ = o;
  num_params_ = static_cast<std::size_t>(o + H + 1);
}

Eigen::VectorXd LstmNet::initial_params(std::uint64_t seed) const {
  std::mt19937_64 rng(seed);
  const double r = 1.0 / std::sqrt(static_cast<double>(shape_.hidden));
  std::uniform_real_distribution<double> u(-r, r);
  Eigen::VectorXd p(static_cast<Eigen::Index>(num_params_));
  for (Eigen::Index i = 0; i < p.size(); ++i) p[i] = u(rng);
  const Eigen::Index H = shape_.hidden;
  for (int l = 0; l < shape_.layers; ++l) {
    const Eigen::Index b = layer_offset_[l] + 4 * H * layer_inputs(l) + 4 * H * H;
    p.segment(b, 4 * H).setZero();
    p.segment(b + H, H).setConstant(1.0);  // remember by default: forget gate open
  }
  p[head_offset_ + H] = 0.0;
  return p;
}

double LstmNet::step(const double* params, const double* x, const double* h_in, const double* c_in, double* h_out,
                     double* c_out) const {
  const int H = shape_.hidden;
  double gbuf[4 * kMaxHidden];
  Eigen::Map<Eigen::VectorXd> g(gbuf, 4 * H);
  const double* input = x;
  for (int l = 0; l < shape_.layers; ++l) {
    const int in = layer_inputs(l);
    const double* p = params + layer_offset_[l];
    Eigen::Map<const Eigen::MatrixXd> W(p, 4 * H, in);
    Eigen::Map<const Eigen::MatrixXd> U(p + 4 * H * in, 4 * H, H);
    Eigen::Map<const Eigen::VectorXd> b(p + 4 * H * in + 4 * H * H, 4 * H);
    g = b;
    g.noalias() += W * Eigen::Map<const Eigen::VectorXd>(input, in);
    g.noalias() += U * Eigen::Map<const Eigen::VectorXd>(h_in + l * H, H);
    for (int j = 0; j < H; ++j) {
      const double i = sigmoid(g[j]), f = sigmoid(g[H + j]), gg = std::tanh(g[2 * H + j]), o = sigmoid(g[3 * H + j]);
      const double c = f * c_in[l * H + j] + i * gg;
      c_out[l * H + j] = c;
      h_out[l * H + j] = o * std::tanh(c);
    }
    input = h_out + l * H;
  }
  const double* w = params + head_offset_;
  double y = w[H];
  for (int j = 0; j < H; ++j) y += w[j] * input[j];
  return y;
}

double LstmNet::sequence_loss_grad(const Eigen::VectorXd& params, const std::vector<Eigen::MatrixXd>& xs,
                                   const Eigen::MatrixXd& ys, int warmup, Eigen::VectorXd* grad) const {
  using Eigen::MatrixXd;
  const Eigen::Index H = shape_.hidden, T = ys.rows(), B = ys.cols();
  const int L = shape_.layers;
  if (static_cast<Eigen::Index>(xs.size()) != warmup + T) throw std::runtime_error("lstm: sequence length mismatch");
  auto W = [&](int l) { return Eigen::Map<const MatrixXd>(params.data() + layer_offset_[l], 4 * H, layer_inputs(l)); };
  auto U = [&](int l) {
    return Eigen::Map<const MatrixXd>(params.data() + layer_offset_[l] + 4 * H * layer_inputs(l), 4 * H, H);
  };
  auto bias = [&](int l) {
    return Eigen::Map<const Eigen::VectorXd>(params.data() + layer_offset_[l] + 4 * H * layer_inputs(l) + 4 * H * H,
                                             4 * H);
  };
  Eigen::Map<const Eigen::VectorXd> wh(params.data() + head_offset_, H);
  const double bh = params[head_offset_ + H];

  std::vector<MatrixXd> h(static_cast<std::size_t>(L), MatrixXd::Zero(H, B)), c = h;
  MatrixXd gates(4 * H, B), tanh_c(H, B);
  // Gate pre-activations → activations in place; then the new c and h.
  auto cell = [&](int l, const MatrixXd& input, MatrixXd& g, MatrixXd& c_l, MatrixXd& h_l) {
    g.noalias() = W(l) * input;
    g.noalias() += U(l) * h_l;
    g.colwise() += bias(l);
    g.topRows(2 * H) = 1.0 / (1.0 + (-g.topRows(2 * H).array()).exp());
    // tanh through the vectorised exp (Eigen's double tanh is scalar): tanh(z) = 2 / (1 + e^{-2z}) - 1.
    g.middleRows(2 * H, H) = 2.0 / (1.0 + (-2.0 * g.middleRows(2 * H, H).array()).exp()) - 1.0;
    g.bottomRows(H) = 1.0 / (1.0 + (-g.bottomRows(H).array()).exp());
    c_l = g.middleRows(H, H).cwiseProduct(c_l) + g.topRows(H).cwiseProduct(g.middleRows(2 * H, H));
    tanh_c = 2.0 / (1.0 + (-2.0 * c_l.array()).exp()) - 1.0;
    h_l = g.bottomRows(H).cwiseProduct(tanh_c);
  };
  for (int tau = 0; tau < warmup; ++tau)
    for (int l = 0; l < L; ++l) cell(l, l == 0 ? xs[static_cast<std::size_t>(tau)] : h[static_cast<std::size_t>(l - 1)],
                                     gates, c[static_cast<std::size_t>(l)], h[static_cast<std::size_t>(l)]);

  const std::vector<MatrixXd> h0 = h, c0 = c;
  const std::size_t steps = static_cast<std::size_t>(T * L);
  std::vector<MatrixXd> G(grad ? steps : 0), C(grad ? steps : 0), Hs(grad ? steps : 0), TC(grad ? steps : 0);
  MatrixXd err(T, B);
  double loss = 0.0;
  for (Eigen::Index t = 0; t < T; ++t) {
    for (int l = 0; l < L; ++l) {
      const auto li = static_cast<std::size_t>(l);
      cell(l, l == 0 ? xs[static_cast<std::size_t>(warmup + t)] : h[li - 1], gates, c[li], h[li]);
      if (grad) {
        const std::size_t k = static_cast<std::size_t>(t * L + l);
        G[k] = gates;
        C[k] = c[li];
        Hs[k] = h[li];
        TC[k] = tanh_c;
      }
    }
    err.row(t) = (wh.transpose() * h[static_cast<std::size_t>(L - 1)]).array() + bh - ys.row(t).array();
  }
  loss = err.squaredNorm();
  if (!grad) return loss;

  Eigen::Map<Eigen::VectorXd> gwh(grad->data() + head_offset_, H);
  double& gbh = (*grad)[head_offset_ + H];
  std::vector<MatrixXd> dh_next(static_cast<std::size_t>(L), MatrixXd::Zero(H, B)), dc_next = dh_next;
  MatrixXd dA(4 * H, B), dh(H, B), dc(H, B), from_above(H, B);
  for (Eigen::Index t = T - 1; t >= 0; --t) {
    const Eigen::RowVectorXd dy = 2.0 * err.row(t);
    gwh.noalias() += Hs[static_cast<std::size_t>(t * L + L - 1)] * dy.transpose();
    gbh += dy.sum();
    from_above.noalias() = wh * dy;
    for (int l = L - 1; l >= 0; --l) {
      const auto li = static_cast<std::size_t>(l);
      const std::size_t k = static_cast<std::size_t>(t * L + l);
      const MatrixXd& g = G[k];
      const MatrixXd& c_prev = t > 0 ? C[k - static_cast<std::size_t>(L)] : c0[li];
      const MatrixXd& h_prev = t > 0 ? Hs[k - static_cast<std::size_t>(L)] : h0[li];
      const auto i = g.topRows(H).array(), f = g.middleRows(H, H).array(), gg = g.middleRows(2 * H, H).array(),
                 o = g.bottomRows(H).array();
      const auto tc = TC[k].array();
      dh = dh_next[li] + from_above;
      dc = dc_next[li].array() + dh.array() * o * (1.0 - tc.square());
      dA.topRows(H) = (dc.array() * gg * i * (1.0 - i)).matrix();
      dA.middleRows(H, H) = (dc.array() * c_prev.array() * f * (1.0 - f)).matrix();
      dA.middleRows(2 * H, H) = (dc.array() * i * (1.0 - gg.square())).matrix();
      dA.bottomRows(H) = (dh.array() * tc * o * (1.0 - o)).matrix();
      dc_next[li] = dc.cwiseProduct(g.middleRows(H, H));
      const MatrixXd& input = l == 0 ? xs[static_cast<std::size_t>(warmup + t)] : Hs[k - 1];
      const int in = layer_inputs(l);
      double* gp = grad->data() + layer_offset_[l];
      Eigen::Map<MatrixXd>(gp, 4 * H, in).noalias() += dA * input.transpose();
      Eigen::Map<MatrixXd>(gp + 4 * H * in, 4 * H, H).noalias() += dA * h_prev.transpose();
      Eigen::Map<Eigen::VectorXd>(gp + 4 * H * in + 4 * H * H, 4 * H) += dA.rowwise().sum();
      dh_next[li].noalias() = U(l).transpose() * dA;
      if (l > 0) from_above.noalias() = W(l).transpose() * dA;
    }
  }
  return loss;
}

// ---- model --------------------------------------------------------------------------------------------------

LstmModel::LstmModel(const features::FeatureSpec& spec, double sample_rate_hz, const LstmShape& shape,
                     Eigen::VectorXd params, TargetScale target, int warmup)
    : stream_(spec, sample_rate_hz), sample_rate_hz_(sample_rate_hz), net_(shape), params_(std::move(params)),
      target_(target), warmup_(warmup) {
  if (static_cast<int>(spec.size()) != shape.inputs)
    throw std::runtime_error("lstm: the feature spec has " + std::to_string(spec.size()) +
                             " features but the network expects " + std::to_string(shape.inputs));
  if (static_cast<std::size_t>(params_.size()) != net_.num_params())
    throw std::runtime_error("lstm: weight count does not match the architecture");
  if (warmup_ < 0) throw std::runtime_error("lstm: warmup must be ≥ 0");
  h_.assign(static_cast<std::size_t>(shape.layers * shape.hidden), 0.0);
  c_ = h_;
  meta.sample_rate_hz = sample_rate_hz;
}

void LstmModel::reset(double voltage_v, double position_nm) {
  stream_.reset(voltage_v, position_nm);
  std::fill(h_.begin(), h_.end(), 0.0);
  std::fill(c_.begin(), c_.end(), 0.0);
  if (!stream_.spec().aux_signals().empty()) return;  // aux values unknown at rest: start from the zero state
  // The same gradient-free warm-up from zero that every training window had, here at rest.
  double x[256];
  stream_.compute(ModelInput{voltage_v, nullptr}, x);
  for (int k = 0; k < warmup_; ++k) net_.step(params_.data(), x, h_.data(), c_.data(), h_.data(), c_.data());
}

double LstmModel::predict(const ModelInput& in) const {
  double x[256], h[LstmNet::kMaxLayers * LstmNet::kMaxHidden], c[LstmNet::kMaxLayers * LstmNet::kMaxHidden];
  stream_.compute(in, x);
  return target_.to_nm(net_.step(params_.data(), x, h_.data(), c_.data(), h, c));
}

void LstmModel::commit(const ModelInput& in, double position_nm) {
  double x[256];
  stream_.compute(in, x);
  net_.step(params_.data(), x, h_.data(), c_.data(), h_.data(), c_.data());
  stream_.commit(in, position_nm);
}

YAML::Node LstmModel::to_yaml() const {
  YAML::Node n;
  n["sample_rate_hz"] = sample_rate_hz_;
  n["features"] = stream_.spec().to_yaml();
  n["target"] = target_.to_yaml();
  n["hyperparameters"]["layers"] = net_.shape().layers;
  n["hyperparameters"]["hidden"] = net_.shape().hidden;
  n["hyperparameters"]["warmup"] = warmup_;
  if (training_info) n["training"] = training_info;
  n["weights"] = yaml_list(params_);
  return n;
}

std::unique_ptr<LstmModel> LstmModel::from_yaml(const YAML::Node& node) {
  const NeuralFileHeader header = read_neural_file_header(node, "lstm", {"layers", "hidden", "warmup"});
  const YAML::Node h = header.hyperparameters;
  LstmShape shape;
  shape.inputs = static_cast<int>(header.spec.size());
  shape.layers = yaml_int(h, "layers", 1, 8, "model.hyperparameters");
  shape.hidden = yaml_int(h, "hidden", 1, 256, "model.hyperparameters");
  const int warmup = yaml_int(h, "warmup", 0, 100000, "model.hyperparameters");
  const LstmNet net(shape);
  const std::vector<double> w = yaml_numbers(node, "weights", static_cast<long>(net.num_params()));
  auto m = std::make_unique<LstmModel>(header.spec, header.sample_rate_hz, shape,
                                       Eigen::Map<const Eigen::VectorXd>(w.data(), static_cast<Eigen::Index>(w.size())),
                                       header.target, warmup);
  if (node["training"]) m->training_info = node["training"];
  return m;
}

}  // namespace piezo::models
