// The one set of typed readers for model-file fields (every kind's loader, the neural file header, the fit
// options' key check). `where` is the path of `node` in the file ("model", "model.hyperparameters"); errors read
// "<where>.<key>: <problem>", and load_model puts the file name in front.
#pragma once

#include <Eigen/Dense>
#include <yaml-cpp/yaml.h>

#include <string>
#include <vector>

namespace piezo::models {

// Throws "<where>: unknown key 'k' (known: …)" when node has a key outside `allowed`.
void check_keys(const YAML::Node& node, const std::vector<std::string>& allowed, const std::string& where = "model");
double yaml_number(const YAML::Node& node, const std::string& key, const std::string& where = "model");  // finite
int yaml_int(const YAML::Node& node, const std::string& key, const std::string& where = "model");
int yaml_int(const YAML::Node& node, const std::string& key, int low, int high, const std::string& where = "model");
std::string yaml_string(const YAML::Node& node, const std::string& key, const std::string& where = "model");
// Finite numbers; exactly `expected_size` of them unless it is negative.
std::vector<double> yaml_numbers(const YAML::Node& node, const std::string& key, long expected_size = -1,
                                 const std::string& where = "model");
// Flow-style lists for writing.
YAML::Node yaml_list(const std::vector<double>& v);
YAML::Node yaml_list(const Eigen::VectorXd& v);

}  // namespace piezo::models
