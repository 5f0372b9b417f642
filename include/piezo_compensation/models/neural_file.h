// What the neural kinds' model files share: the target standardisation with its output rails, the common
// header of the `model:` node (kind, rate, feature spec, target, hyperparameters), and typed YAML field readers.
#pragma once

#include <Eigen/Dense>
#include <yaml-cpp/yaml.h>

#include <limits>
#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/models/yaml_fields.h"

namespace piezo::models {

// Position standardisation of a network's output: position_nm = mean_nm + scale_nm · z, held to the rails.
struct TargetScale {
  double mean_nm = 0.0;
  double scale_nm = 1.0;
  // Output rails: the training range widened by half its span each side. Networks extrapolate without bound;
  // fed back in free-run they can run away to ±inf, so outputs are held to physically plausible values.
  double output_min_nm = -std::numeric_limits<double>::infinity();
  double output_max_nm = std::numeric_limits<double>::infinity();
  double to_nm(double z) const {
    const double y = mean_nm + scale_nm * z;
    return y < output_min_nm ? output_min_nm : (y > output_max_nm ? output_max_nm : y);
  }
  double to_z(double nm) const { return (nm - mean_nm) / scale_nm; }
  YAML::Node to_yaml() const;
  static TargetScale from_yaml(const YAML::Node& node, const std::string& where);  // rails optional
  std::string c99_expression(const std::string& z) const;  // to_nm in C
};
// What every neural kind's model-file node shares, read and checked in one place: the kind, the sample rate, the
// feature spec, the target scale and the hyperparameters map (keys checked against `hyperparameter_keys`).
// `extra_keys` are the kind's own further top-level keys (e.g. KAN's "grids"). Errors name the path ("model.target.scale_nm").
struct NeuralFileHeader {
  double sample_rate_hz = 0.0;
  features::FeatureSpec spec;
  TargetScale target;
  YAML::Node hyperparameters;
};
NeuralFileHeader read_neural_file_header(const YAML::Node& node, const std::string& kind,
                                         const std::vector<std::string>& hyperparameter_keys,
                                         const std::vector<std::string>& extra_keys = {});

}  // namespace piezo::models
