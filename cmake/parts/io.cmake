# io/: Dataset and CSV.
piezo_unit_test(test_io_csv test/unit/test_io_csv.cpp)
piezo_unit_test(test_io_pairer test/unit/test_io_pairer.cpp)
# util/: the child-process helper (no shell).
piezo_unit_test(test_util_child_process test/unit/test_util_child_process.cpp)
