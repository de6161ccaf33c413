/* Host-side access to the firmware core for tests/test_firmware.py (ctypes): the sizes of the core's
 * structs, so Python can allocate them, and their counters. Not part of any firmware image. */
#include <stddef.h>

#include "daq.h"
#include "input.h"

size_t shim_daq_size(void);
size_t shim_input_size(void);
size_t shim_ring_size(void);
unsigned shim_ring_capacity(void);
fw_counters *shim_counters(fw_daq *d);
fw_ring *shim_ring(fw_daq *d);
uint32_t shim_input_bad_crc(const fw_input *p);

size_t shim_daq_size(void) { return sizeof(fw_daq); }
size_t shim_input_size(void) { return sizeof(fw_input); }
size_t shim_ring_size(void) { return sizeof(fw_ring); }
unsigned shim_ring_capacity(void) { return FW_RING_CAPACITY; }
fw_counters *shim_counters(fw_daq *d) { return &d->c; }
fw_ring *shim_ring(fw_daq *d) { return &d->ring; }
uint32_t shim_input_bad_crc(const fw_input *p) { return p->bad_crc; }
