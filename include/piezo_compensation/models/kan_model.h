// Kolmogorov–Arnold network: every edge i→j of every layer carries its own learnable function
//   φ(x) = w_b · SiLU(x) + Σ_k c_k B_k(x)
// (B_k the B-splines of order `order` on a grid of `grid` intervals per input node, extended by `order` knots
// each side), node outputs are sums of incoming edges plus a bias. Grids adapt to the data (quantiles mixed
// with a uniform grid, coefficients refitted by least squares so the functions stay the same). Each edge's
// learned function can be printed as a simple formula (polynomial ≤ 3, sin, exp, log, tanh, fitted by least
// squares with its R²). Kind "kan".
#pragma once

#include <Eigen/Dense>

#include <cstdint>
#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/neural_file.h"

namespace piezo::models {

struct KanShape {
  std::vector<int> widths{1, 4, 1};  // inputs, hidden…, 1
  int grid = 5;                      // intervals
  int order = 3;                     // spline order (3 = cubic)
};

// The order+1 B-spline basis values (and derivatives, may be null) at x on `knots` that can be non-zero: basis
// functions first … first+order (indices outside 0 … num_knots−order−2 carry zero). Returns false when x is
// outside [t_0, t_last) (every basis function is zero there).
bool bspline_basis(const double* knots, int num_knots, int order, double x, int* first, double* values,
                   double* derivatives);

// Parameters, per layer, per edge (in-major: edge = i * out + j): w_b, then G + k coefficients; then per layer
// the output biases. The grids are state, not parameters.
class KanNet {
 public:
  static constexpr int kMaxWidth = 64;
  KanNet() = default;
  explicit KanNet(const KanShape& shape);  // uniform grids on [-2, 2] (standardised inputs)
  const KanShape& shape() const { return shape_; }
  std::size_t num_params() const { return num_params_; }
  int num_layers() const { return static_cast<int>(shape_.widths.size()) - 1; }
  int num_basis() const { return shape_.grid + shape_.order; }
  int num_knots() const { return shape_.grid + 2 * shape_.order + 1; }
  Eigen::VectorXd initial_params(std::uint64_t seed) const;

  // Knots of input node i of layer l (num_knots() values).
  const double* knots(int layer, int input) const;
  const std::vector<std::vector<double>>& grids() const { return grids_; }  // per layer: inputs × num_knots()
  void set_grid(int layer, std::vector<double> knots);  // throws unless sized and strictly increasing per node

  // One edge's function value.
  double edge(const double* params, int layer, int input, int output, double x) const;
  double forward(const double* params, const double* x) const;  // one sample, no allocation
  double loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x, const Eigen::VectorXd& y,
                   Eigen::VectorXd* grad) const;

  // Grid update from data (columns of x): new knots per input node from the node's sample quantiles mixed
  // with a uniform grid (weight grid_eps), spline coefficients refitted so every edge keeps its function.
  void update_grids(Eigen::VectorXd& params, const Eigen::MatrixXd& x, double grid_eps = 0.02);

  Eigen::Index edge_offset(int layer, int input, int output) const;
  Eigen::Index bias_offset(int layer) const { return bias_offset_[static_cast<std::size_t>(layer)]; }

 private:
  KanShape shape_;
  std::size_t num_params_ = 0;
  std::vector<Eigen::Index> layer_offset_, bias_offset_;
  std::vector<std::vector<double>> grids_;
  // 1 / (t[i+j] − t[i]) for j = 1 … order, per layer and input node: multiplications instead of divisions.
  std::vector<std::vector<double>> inv_spans_;
  void update_inv_spans(int layer);
  bool basis(int layer, int input, double x, int* first, double* values, double* derivatives) const;
  // Node values of every layer for the columns of x (layer 0 = x).
  std::vector<Eigen::MatrixXd> activations(const Eigen::VectorXd& params, const Eigen::MatrixXd& x) const;
};

// A closed-form stand-in for one learned function.
struct SymbolicFit {
  std::string family;        // "x", "x^2", "x^3", "sin", "tanh", "exp", "log"
  std::vector<double> coef;  // polynomials: c0…c3; others: a, b, c, d of a·f(b·x + c) + d
  double r2 = 0.0;
  std::string formula(const std::string& var) const;
};
// Best formula for samples y(x): the simplest family within 1e-4 of the best R².
SymbolicFit fit_symbolic(const std::vector<double>& x, const std::vector<double>& y);

class KanModel : public Model {
 public:
  KanModel(const features::FeatureSpec& spec, double sample_rate_hz, KanNet net, Eigen::VectorXd params,
           TargetScale target);
  std::string kind() const override { return "kan"; }
  void reset(double voltage_v, double position_nm) override { stream_.reset(voltage_v, position_nm); }
  double predict(const ModelInput& in) const override;
  void commit(const ModelInput& in, double position_nm) override { stream_.commit(in, position_nm); }
  std::unique_ptr<Model> clone() const override { return std::make_unique<KanModel>(*this); }
  bool uses_position_history() const override { return stream_.spec().uses_positions(); }
  std::string fixed_rate_reason() const override { return kLaggedSamplesReason; }
  std::vector<std::string> aux_inputs() const override { return stream_.spec().aux_signals(); }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override { return net_.num_params(); }
  static std::unique_ptr<KanModel> from_yaml(const YAML::Node& node);

  // One line per edge: "layer 0, z2 → h1: 0.41·sin(1.2·z2 + 0.3) - 0.02  (R² 0.9993)", with the legend
  // z_i = (feature_i − mean_i) / scale_i. Edges sampled over their grid range.
  std::string formulas() const;
  std::string export_c99_network(const std::string& prefix) const;  // network on the standardised features
  std::string export_c99(const std::string& prefix) const;          // streaming header (neural_c99_header)
  const KanNet& net() const { return net_; }
  const Eigen::VectorXd& params() const { return params_; }
  YAML::Node training_info;

 private:
  features::FeatureStream stream_;
  double sample_rate_hz_;
  KanNet net_;
  Eigen::VectorXd params_;
  TargetScale target_;
};

}  // namespace piezo::models
