#include "piezo_compensation/ros/params.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::params {

namespace {

template <typename T>
std::string str(T v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

std::string join(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
  return s;
}

bool as_number(const XmlRpc::XmlRpcValue& v, double& out) {
  if (v.getType() == XmlRpc::XmlRpcValue::TypeDouble) {
    out = static_cast<double>(const_cast<XmlRpc::XmlRpcValue&>(v));
    return true;
  }
  if (v.getType() == XmlRpc::XmlRpcValue::TypeInt) {
    out = static_cast<int>(const_cast<XmlRpc::XmlRpcValue&>(v));
    return true;
  }
  return false;
}

}  // namespace

std::string ParamReader::first_component(const std::string& name) {
  std::string n = name;
  if (!n.empty() && n.front() == '~') n.erase(0, 1);
  while (!n.empty() && n.front() == '/') n.erase(0, 1);
  return n.substr(0, n.find('/'));
}

bool ParamReader::fetch(const std::string& name, XmlRpc::XmlRpcValue& value) {
  read_.insert(first_component(name));
  return nh_.hasParam(name) && nh_.getParam(name, value);
}

double ParamReader::number(const std::string& name, double fallback, double min, double max) {
  XmlRpc::XmlRpcValue v;
  double out = fallback;
  if (fetch(name, v) && !as_number(v, out))
    throw std::invalid_argument("parameter " + resolved(name) + " must be a number");
  if (!std::isfinite(out) || out < min || out > max)
    throw std::invalid_argument("parameter " + resolved(name) + " = " + str(out) + " is outside [" + str(min) + ", " +
                                str(max) + "]");
  return out;
}

int ParamReader::integer(const std::string& name, int fallback, int min, int max) {
  XmlRpc::XmlRpcValue v;
  int out = fallback;
  if (fetch(name, v)) {
    if (v.getType() != XmlRpc::XmlRpcValue::TypeInt)
      throw std::invalid_argument("parameter " + resolved(name) + " must be an integer");
    out = static_cast<int>(v);
  }
  if (out < min || out > max)
    throw std::invalid_argument("parameter " + resolved(name) + " = " + str(out) + " is outside [" + str(min) + ", " +
                                str(max) + "]");
  return out;
}

bool ParamReader::flag(const std::string& name, bool fallback) {
  XmlRpc::XmlRpcValue v;
  if (!fetch(name, v)) return fallback;
  if (v.getType() != XmlRpc::XmlRpcValue::TypeBoolean)
    throw std::invalid_argument("parameter " + resolved(name) + " must be true or false");
  return static_cast<bool>(v);
}

std::string ParamReader::text(const std::string& name, const std::string& fallback,
                              const std::vector<std::string>& allowed) {
  XmlRpc::XmlRpcValue v;
  std::string out = fallback;
  if (fetch(name, v)) {
    if (v.getType() != XmlRpc::XmlRpcValue::TypeString)
      throw std::invalid_argument("parameter " + resolved(name) + " must be a string");
    out = static_cast<std::string>(v);
  }
  if (!allowed.empty() && std::find(allowed.begin(), allowed.end(), out) == allowed.end())
    throw std::invalid_argument("parameter " + resolved(name) + " = \"" + out + "\" must be one of: " + join(allowed));
  return out;
}

std::vector<double> ParamReader::numbers(const std::string& name, const std::vector<double>& fallback, double min,
                                         double max, std::size_t min_count, std::size_t max_count) {
  XmlRpc::XmlRpcValue v;
  std::vector<double> out = fallback;
  if (fetch(name, v)) {
    if (v.getType() != XmlRpc::XmlRpcValue::TypeArray)
      throw std::invalid_argument("parameter " + resolved(name) + " must be a list of numbers");
    out.clear();
    for (int i = 0; i < v.size(); ++i) {
      double x = 0.0;
      if (!as_number(v[i], x))
        throw std::invalid_argument("parameter " + resolved(name) + "[" + str(i) + "] must be a number");
      out.push_back(x);
    }
  }
  if (out.size() < min_count || out.size() > max_count)
    throw std::invalid_argument("parameter " + resolved(name) + " has " + str(out.size()) + " entries, needs " +
                                str(min_count) + ".." + str(max_count));
  for (std::size_t i = 0; i < out.size(); ++i)
    if (!std::isfinite(out[i]) || out[i] < min || out[i] > max)
      throw std::invalid_argument("parameter " + resolved(name) + "[" + str(i) + "] = " + str(out[i]) +
                                  " is outside [" + str(min) + ", " + str(max) + "]");
  return out;
}

std::vector<std::string> ParamReader::texts(const std::string& name, const std::vector<std::string>& fallback,
                                            const std::vector<std::string>& allowed, std::size_t min_count,
                                            std::size_t max_count) {
  XmlRpc::XmlRpcValue v;
  std::vector<std::string> out = fallback;
  if (fetch(name, v)) {
    if (v.getType() != XmlRpc::XmlRpcValue::TypeArray)
      throw std::invalid_argument("parameter " + resolved(name) + " must be a list of strings, e.g. [" +
                                  (allowed.empty() ? std::string("\"x\"") : "\"" + allowed.front() + "\"") + "]");
    out.clear();
    for (int i = 0; i < v.size(); ++i) {
      if (v[i].getType() != XmlRpc::XmlRpcValue::TypeString)
        throw std::invalid_argument("parameter " + resolved(name) + "[" + str(i) + "] must be a string");
      out.push_back(static_cast<std::string>(v[i]));
    }
  }
  if (out.size() < min_count || out.size() > max_count)
    throw std::invalid_argument("parameter " + resolved(name) + " has " + str(out.size()) + " entries, needs " +
                                str(min_count) + ".." + str(max_count));
  for (std::size_t i = 0; i < out.size(); ++i) {
    if (!allowed.empty() && std::find(allowed.begin(), allowed.end(), out[i]) == allowed.end())
      throw std::invalid_argument("parameter " + resolved(name) + "[" + str(i) + "] = \"" + out[i] +
                                  "\" must be one of: " + join(allowed));
    if (std::find(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(i), out[i]) !=
        out.begin() + static_cast<std::ptrdiff_t>(i))
      throw std::invalid_argument("parameter " + resolved(name) + " names \"" + out[i] + "\" twice");
  }
  return out;
}

std::vector<std::string> ParamReader::unknown() const {
  std::vector<std::string> all;
  if (!nh_.getParamNames(all)) return {};
  std::string prefix = nh_.getNamespace();
  if (prefix.empty() || prefix.back() != '/') prefix += '/';
  std::set<std::string> unread;
  for (const auto& full : all) {
    if (full.compare(0, prefix.size(), prefix) != 0) continue;
    const std::string first = first_component(full.substr(prefix.size()));
    if (!first.empty() && read_.count(first) == 0) unread.insert(first);
  }
  return {unread.begin(), unread.end()};
}

std::size_t ParamReader::warn_unknown(const std::string& node_name) const {
  const auto names = unknown();
  for (const auto& n : names)
    ROS_WARN_STREAM(node_name << ": unknown parameter " << resolved(n)
                              << " is ignored (misspelt? the node's parameters are documented in config/)");
  return names.size();
}

}  // namespace piezo::params
