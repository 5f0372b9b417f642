// Content hash of a data set (FNV-1a 64 over the numeric columns), stored in model files to tell which data a
// model was fitted on. Same numbers in the same order give the same fingerprint, whatever the file format.
#pragma once

#include <cstdint>
#include <string>

#include "piezo_compensation/io/dataset.h"

namespace piezo::util {

std::uint64_t fnv1a64(const void* data, std::size_t bytes, std::uint64_t h = 1469598103934665603ULL);
// "fnv1a64:<16 hex digits>:<samples>"
std::string fingerprint(const io::Dataset& data);

}  // namespace piezo::util
