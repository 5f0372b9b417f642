# io/: Dataset and CSV, the hold finder.
piezo_unit_test(test_io_csv test/unit/test_io_csv.cpp)
piezo_unit_test(test_io_holds test/unit/test_io_holds.cpp)
piezo_unit_test(test_io_pairer test/unit/test_io_pairer.cpp)
# util/: the child-process helper (no shell), the subnormal flush guard.
piezo_unit_test(test_util_child_process test/unit/test_util_child_process.cpp)
piezo_unit_test(test_util_flush_subnormals test/unit/test_util_flush_subnormals.cpp)
