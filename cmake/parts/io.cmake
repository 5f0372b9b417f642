# io/: Dataset and CSV.
piezo_unit_test(test_io_csv test/unit/test_io_csv.cpp)
piezo_unit_test(test_io_pairer test/unit/test_io_pairer.cpp)
