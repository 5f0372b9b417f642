#include "piezo_compensation/ros/params.h"
#include "piezo_compensation/util/format.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
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

std::string num(double v) { return util::fmt(v, 10); }

std::string list_of(const std::vector<double>& v) {
  std::string s;
  for (double x : v) s += (s.empty() ? "" : ", ") + num(x);
  return "[" + s + "]";
}

std::string quoted_list(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
  return "[" + s + "]";
}

std::string count_range(std::size_t lo, std::size_t hi) {
  return lo == hi ? str(lo) + " entries" : str(lo) + ".." + str(hi) + " entries";
}

ParamDef base(const std::string& name, ParamType type, const std::string& unit, const std::string& meaning) {
  ParamDef d;
  d.name = name;
  d.type = type;
  d.unit = unit;
  d.meaning = meaning;
  return d;
}

}  // namespace

ParamDef number(const std::string& name, const std::string& unit, double fallback, double min, double max,
                const std::string& meaning) {
  ParamDef d = base(name, ParamType::kNumber, unit, meaning);
  d.number = fallback, d.min = min, d.max = max;
  return d;
}

ParamDef integer(const std::string& name, const std::string& unit, int fallback, int min, int max,
                 const std::string& meaning) {
  ParamDef d = base(name, ParamType::kInteger, unit, meaning);
  d.number = fallback, d.min = min, d.max = max;
  return d;
}

ParamDef flag(const std::string& name, bool fallback, const std::string& meaning) {
  ParamDef d = base(name, ParamType::kFlag, "", meaning);
  d.flag = fallback;
  return d;
}

ParamDef text(const std::string& name, const std::string& fallback, const std::string& meaning,
              const std::vector<std::string>& allowed) {
  ParamDef d = base(name, ParamType::kText, "", meaning);
  d.text = fallback, d.allowed = allowed;
  return d;
}

ParamDef numbers(const std::string& name, const std::string& unit, const std::vector<double>& fallback, double min,
                 double max, std::size_t min_count, std::size_t max_count, const std::string& meaning) {
  ParamDef d = base(name, ParamType::kNumbers, unit, meaning);
  d.numbers = fallback, d.min = min, d.max = max, d.min_count = min_count, d.max_count = max_count;
  return d;
}

ParamDef texts(const std::string& name, const std::vector<std::string>& fallback,
               const std::vector<std::string>& allowed, std::size_t min_count, std::size_t max_count,
               const std::string& meaning) {
  ParamDef d = base(name, ParamType::kTexts, "", meaning);
  d.texts = fallback, d.allowed = allowed, d.min_count = min_count, d.max_count = max_count;
  return d;
}

ParamDef structured(const std::string& name, const std::string& unit, const std::string& shape,
                    const std::string& default_text, const std::string& meaning) {
  ParamDef d = base(name, ParamType::kMap, unit, meaning);
  d.text = shape, d.default_text = default_text;
  return d;
}

std::string ParamDef::type_name() const {
  switch (type) {
    case ParamType::kNumber: return "double";
    case ParamType::kInteger: return "int";
    case ParamType::kFlag: return "bool";
    case ParamType::kText: return "string";
    case ParamType::kNumbers: return "double[]";
    case ParamType::kTexts: return "string[]";
    case ParamType::kMap: return text;
  }
  return "";
}

std::string ParamDef::default_string() const {
  if (!default_text.empty()) return default_text;
  switch (type) {
    case ParamType::kNumber:
    case ParamType::kInteger: return num(number);
    case ParamType::kFlag: return flag ? "true" : "false";
    case ParamType::kText: return "\"" + text + "\"";
    case ParamType::kNumbers: return list_of(numbers);
    case ParamType::kTexts: return quoted_list(texts);
    case ParamType::kMap: return "";
  }
  return "";
}

std::string ParamDef::range_string() const {
  std::string r;
  switch (type) {
    case ParamType::kNumber:
    case ParamType::kInteger: r = "[" + num(min) + ", " + num(max) + "]"; break;
    case ParamType::kFlag: break;
    case ParamType::kText: r = allowed.empty() ? "" : "one of: " + join(allowed); break;
    case ParamType::kNumbers: r = count_range(min_count, max_count) + ", each in [" + num(min) + ", " + num(max) + "]"; break;
    case ParamType::kTexts:
      r = count_range(min_count, max_count) + (allowed.empty() ? "" : ", each one of: " + join(allowed)) + ", no repeats";
      break;
    case ParamType::kMap: break;
  }
  if (!constraint.empty()) r += (r.empty() ? "" : "; ") + constraint;
  return r;
}

std::string TopicDef::for_axis(const std::string& axis) const {
  const std::string key = "<axis>";
  const auto at = name.find(key);
  if (at == std::string::npos) return name;
  if (axis.empty()) throw std::logic_error("topic " + name + " is per axis: give the axis");
  return name.substr(0, at) + axis + name.substr(at + key.size());
}

template <typename T>
const T& find_entry(const std::vector<T>& v, const std::string& name, const std::string& node, const char* what) {
  for (const auto& e : v)
    if (e.name == name) return e;
  throw std::logic_error(node + ": " + what + " '" + name + "' is not in the node's interface table");
}

const ParamDef& NodeInterface::param(const std::string& name) const { return find_entry(params, name, node, "parameter"); }
const TopicDef& NodeInterface::topic(const std::string& name) const { return find_entry(topics, name, node, "topic"); }
const ServiceDef& NodeInterface::service(const std::string& name) const {
  return find_entry(services, name, node, "service");
}

void NodeInterface::check_type(const std::string& name, const std::string& declared, const std::string& used) const {
  if (declared != used)
    throw std::logic_error(node + ": " + name + " is declared " + declared + " but used as " + used);
}

const NodeInterface& ParamReader::table() const {
  if (!table_) throw std::logic_error("ParamReader: no interface table given");
  return *table_;
}

const ParamDef& ParamReader::def(const std::string& name, ParamType type) const {
  const ParamDef& d = table().param(name);
  if (d.type != type)
    throw std::logic_error(table().node + ": parameter " + name + " is declared " + d.type_name() + " but read as " +
                           base(name, type, "", "").type_name());
  return d;
}

double ParamReader::number(const std::string& name) { return number(name, def(name, ParamType::kNumber).number); }
double ParamReader::number(const std::string& name, double fallback) {
  const ParamDef& d = def(name, ParamType::kNumber);
  return number(name, fallback, d.min, d.max);
}
int ParamReader::integer(const std::string& name) {
  return integer(name, static_cast<int>(def(name, ParamType::kInteger).number));
}
int ParamReader::integer(const std::string& name, int fallback) {
  const ParamDef& d = def(name, ParamType::kInteger);
  return integer(name, fallback, static_cast<int>(d.min), static_cast<int>(d.max));
}
bool ParamReader::flag(const std::string& name) { return flag(name, def(name, ParamType::kFlag).flag); }
std::string ParamReader::text(const std::string& name) {
  const ParamDef& d = def(name, ParamType::kText);
  return text(name, d.text, d.allowed);
}
std::vector<double> ParamReader::numbers(const std::string& name) {
  return numbers(name, def(name, ParamType::kNumbers).numbers);
}
std::vector<double> ParamReader::numbers(const std::string& name, const std::vector<double>& fallback) {
  const ParamDef& d = def(name, ParamType::kNumbers);
  return numbers(name, fallback, d.min, d.max, d.min_count, d.max_count);
}
std::vector<std::string> ParamReader::texts(const std::string& name) {
  const ParamDef& d = def(name, ParamType::kTexts);
  return texts(name, d.texts, d.allowed, d.min_count, d.max_count);
}
const ParamDef& ParamReader::structured(const std::string& name) {
  const ParamDef& d = def(name, ParamType::kMap);
  known(name);
  return d;
}

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
                              << " is ignored (misspelt? the node's parameters: docs/ros_interface.md)");
  return names.size();
}

}  // namespace piezo::params
