// A small declarative option parser for the CLI subcommands, with generated --help.
#pragma once

#include <cmath>
#include <cstdlib>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace piezo::cli {

class UsageError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class Args {
 public:
  Args(std::string command, std::string description) : command_(std::move(command)), description_(std::move(description)) {}

  // Declare options before parse(). `meta` empty = flag without a value.
  Args& option(const std::string& name, const std::string& meta, const std::string& help, const std::string& def = "",
               bool repeatable = false) {
    opts_.push_back({name, meta, help, def, repeatable, {}, false});
    return *this;
  }
  Args& required(const std::string& name, const std::string& meta, const std::string& help) {
    opts_.push_back({name, meta, help, "", false, {}, false, true});
    return *this;
  }
  // Files: one or more values after the option (`--data A.csv B.csv`), up to the next option; the option may also
  // be repeated. Read them with list().
  Args& files(const std::string& name, const std::string& meta, const std::string& help, bool is_required) {
    opts_.push_back({name, meta, help, "", true, {}, false, is_required, true});
    return *this;
  }

  // Returns false when --help was printed (caller returns 0). Throws UsageError on bad options.
  bool parse(int argc, char** argv) {
    for (int i = 1; i < argc; ++i) {
      std::string a = argv[i];
      if (a == "-h" || a == "--help") {
        print_help(std::cout);
        return false;
      }
      if (a.rfind("--", 0) != 0) {
        positional_.push_back(a);
        continue;
      }
      std::string value;
      bool has_inline = false;
      auto eq = a.find('=');
      if (eq != std::string::npos) {
        value = a.substr(eq + 1);
        a = a.substr(0, eq);
        has_inline = true;
      }
      Opt* o = find(a.substr(2));
      if (!o) throw UsageError(command_ + ": unknown option " + a + " (see --help)");
      if (o->meta.empty()) {
        o->values.push_back("1");
      } else {
        if (!has_inline) {
          if (i + 1 >= argc) throw UsageError(command_ + ": option " + a + " needs a value " + o->meta);
          value = argv[++i];
        }
        if (!o->repeatable && !o->values.empty()) throw UsageError(command_ + ": option " + a + " given twice");
        o->values.push_back(value);
        while (o->greedy && !has_inline && i + 1 < argc && std::string(argv[i + 1]).rfind("--", 0) != 0)
          o->values.push_back(argv[++i]);
      }
      o->given = true;
    }
    for (auto& o : opts_)
      if (o.is_required && !o.given)
        throw UsageError(command_ + ": missing required option --" + o.name + " " + o.meta + " (see --help)");
    return true;
  }

  bool has(const std::string& name) const { return get_opt(name).given; }
  std::string str(const std::string& name) const {
    const Opt& o = get_opt(name);
    return o.values.empty() ? o.def : o.values.back();
  }
  std::vector<std::string> list(const std::string& name) const {
    const Opt& o = get_opt(name);
    if (!o.values.empty()) return o.values;
    if (!o.def.empty()) return {o.def};
    return {};
  }
  double num(const std::string& name) const {
    const std::string s = str(name);
    char* end = nullptr;
    double v = std::strtod(s.c_str(), &end);
    if (s.empty() || *end != '\0') throw UsageError(command_ + ": --" + name + " expects a number, got '" + s + "'");
    return v;
  }
  // A duration in seconds: plain seconds ("90", "1.5e3") or a number with a unit: s, min, h, d ("26h", "90min").
  double seconds(const std::string& name) const {
    const std::string s = str(name);
    const double v = parse_duration_s(s);
    if (!std::isfinite(v))
      throw UsageError(command_ + ": --" + name + " expects a duration such as 30, 30s, 90min, 26h or 2d, got '" + s +
                       "'");
    return v;
  }
  // NaN when `s` is not a duration.
  static double parse_duration_s(const std::string& s) {
    const char* begin = s.c_str();
    char* end = nullptr;
    const double v = std::strtod(begin, &end);
    if (s.empty() || end == begin || !std::isfinite(v)) return std::nan("");
    const std::string unit(end);
    if (unit.empty() || unit == "s") return v;
    if (unit == "min") return v * 60.0;
    if (unit == "h") return v * 3600.0;
    if (unit == "d") return v * 86400.0;
    return std::nan("");
  }
  long integer(const std::string& name) const {
    const std::string s = str(name);
    char* end = nullptr;
    long v = std::strtol(s.c_str(), &end, 10);
    if (s.empty() || *end != '\0') throw UsageError(command_ + ": --" + name + " expects an integer, got '" + s + "'");
    return v;
  }
  bool flag(const std::string& name) const { return get_opt(name).given; }
  const std::vector<std::string>& positional() const { return positional_; }

  void print_help(std::ostream& os) const {
    os << "usage: piezo " << command_ << " [options]\n\n" << description_ << "\n\noptions:\n";
    for (const auto& o : opts_) {
      std::ostringstream left;
      left << "  --" << o.name << (o.meta.empty() ? "" : " " + o.meta);
      std::string l = left.str();
      os << l << std::string(l.size() < 30 ? 30 - l.size() : 1, ' ') << o.help;
      if (o.is_required) os << " (required)";
      if (!o.def.empty()) os << " [default: " << o.def << "]";
      if (o.greedy) os << " (one or more)";
      else if (o.repeatable) os << " (repeatable)";
      os << "\n";
    }
    os << "  --help                      this text\n";
  }

 private:
  struct Opt {
    std::string name, meta, help, def;
    bool repeatable = false;
    std::vector<std::string> values;
    bool given = false;
    bool is_required = false;
    bool greedy = false;
  };
  Opt* find(const std::string& n) {
    for (auto& o : opts_)
      if (o.name == n) return &o;
    return nullptr;
  }
  const Opt& get_opt(const std::string& n) const {
    for (const auto& o : opts_)
      if (o.name == n) return o;
    throw std::logic_error("option --" + n + " not declared");
  }
  std::string command_, description_;
  std::vector<Opt> opts_;
  std::vector<std::string> positional_;
};

}  // namespace piezo::cli
