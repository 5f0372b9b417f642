#include "piezo_compensation/nanocontrol/link_state.h"

#include <cstdio>

namespace piezo::nanocontrol {

const char* to_string(Outcome outcome) {
  switch (outcome) {
    case Outcome::kOk: return "ok";
    case Outcome::kRefused: return "refused (e)";
    case Outcome::kInfo: return "info (i)";
    case Outcome::kTimeout: return "no reply";
    case Outcome::kGarbled: return "garbled reply";
  }
  return "?";
}

Exchange classify(const std::string& command, const std::optional<std::string>& line) {
  Exchange e;
  e.command = command;
  if (!line) {
    e.outcome = Outcome::kTimeout;
    return e;
  }
  std::string error;
  const auto reply = parse_reply(*line, &error);
  if (!reply) {
    e.outcome = Outcome::kGarbled;
    e.message = error;
    return e;
  }
  e.message = reply->message;
  switch (reply->status) {
    case ReplyStatus::kOk: e.outcome = Outcome::kOk; break;
    case ReplyStatus::kError: e.outcome = Outcome::kRefused; break;
    case ReplyStatus::kInfo: e.outcome = Outcome::kInfo; break;
  }
  return e;
}

void LinkState::reset() {
  counters_.breakdown = false;
  needs_drain_ = true;
}

bool LinkState::record(const Exchange& e, double reply_timeout_s) {
  ++counters_.exchanges;
  const std::string what = "`" + e.command + "`: ";
  switch (e.outcome) {
    case Outcome::kOk:
      ++counters_.ok;
      return true;
    case Outcome::kRefused:
      ++counters_.refused;
      counters_.last_refusal = what + (e.message.empty() ? "(no message)" : e.message);
      return false;
    case Outcome::kInfo:
      ++counters_.infos;
      ++counters_.breakdowns;
      counters_.breakdown = true;
      counters_.last_info = what + (e.message.empty() ? "(no message)" : e.message);
      return false;
    case Outcome::kTimeout: {
      ++counters_.timeouts;
      char buf[64];
      std::snprintf(buf, sizeof buf, "no reply within %.3g s", reply_timeout_s);
      counters_.last_timeout = what + buf;
      needs_drain_ = true;
      return false;
    }
    case Outcome::kGarbled:
      ++counters_.garbled;
      counters_.last_garbled = what + e.message;
      needs_drain_ = true;
      return false;
  }
  return false;
}

void LinkState::sample_done(bool complete) {
  if (complete)
    ++counters_.samples;
  else
    ++counters_.samples_dropped;
}

}  // namespace piezo::nanocontrol
