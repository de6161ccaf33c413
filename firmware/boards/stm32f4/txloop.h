/* The transmit path, shared by both boards: frames from the sampler's ring out on USART1. A test build with
 * -DFW_TX_PER_1000=N lets it send at most N frames per 1000 sample periods, a link slower than the ADC, to
 * force the overrun (tests/test_firmware.py): the ring fills and the samples it cannot take are dropped and
 * counted, each a counter gap on the host. */
#ifndef FW_TXLOOP_H
#define FW_TXLOOP_H

#include "daq.h"

/* Send every queued frame the link may take now; returns at once when there is none. */
void tx_pump(fw_daq *d);

/* tx_pump forever, sleeping (WFI) until an interrupt has queued a sample. */
__attribute__((noreturn)) void tx_loop(fw_daq *d);

#endif
