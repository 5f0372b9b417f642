#include "piezo_compensation/util/json_writer.h"

#include <cmath>
#include <cstdio>

namespace piezo::util {

std::string JsonWriter::escape(const std::string& s) {
  std::string o = "\"";
  for (unsigned char c : s) {
    switch (c) {
      case '"': o += "\\\""; break;
      case '\\': o += "\\\\"; break;
      case '\n': o += "\\n"; break;
      case '\t': o += "\\t"; break;
      case '\r': o += "\\r"; break;
      default:
        if (c < 0x20) {
          char b[8];
          std::snprintf(b, sizeof b, "\\u%04x", c);
          o += b;
        } else {
          o += static_cast<char>(c);
        }
    }
  }
  return o + "\"";
}

void JsonWriter::before_value() {
  if (after_key_) {
    after_key_ = false;
    return;
  }
  if (!first_.empty()) {
    if (!first_.back()) os_ << ",";
    first_.back() = false;
  }
}

JsonWriter& JsonWriter::begin_object() {
  before_value();
  os_ << "{";
  first_.push_back(true);
  return *this;
}
JsonWriter& JsonWriter::end_object() {
  first_.pop_back();
  os_ << "}";
  return *this;
}
JsonWriter& JsonWriter::begin_array() {
  before_value();
  os_ << "[";
  first_.push_back(true);
  return *this;
}
JsonWriter& JsonWriter::end_array() {
  first_.pop_back();
  os_ << "]";
  return *this;
}
JsonWriter& JsonWriter::key(const std::string& k) {
  before_value();
  os_ << escape(k) << ":";
  after_key_ = true;
  return *this;
}
JsonWriter& JsonWriter::value(double v) {
  before_value();
  if (!std::isfinite(v)) {
    os_ << "null";
  } else {
    char b[32];
    std::snprintf(b, sizeof b, "%.10g", v);
    os_ << b;
  }
  return *this;
}
JsonWriter& JsonWriter::value(long long v) {
  before_value();
  os_ << v;
  return *this;
}
JsonWriter& JsonWriter::value(bool v) {
  before_value();
  os_ << (v ? "true" : "false");
  return *this;
}
JsonWriter& JsonWriter::value(const std::string& v) {
  before_value();
  os_ << escape(v);
  return *this;
}
JsonWriter& JsonWriter::null() {
  before_value();
  os_ << "null";
  return *this;
}
JsonWriter& JsonWriter::array(const std::vector<double>& v) {
  begin_array();
  for (double x : v) value(x);
  return end_array();
}

}  // namespace piezo::util
