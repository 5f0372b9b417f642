// Compiles the unit tests' shared precompiled header (cmake/piezo_helpers.cmake: piezo_test_pch).
