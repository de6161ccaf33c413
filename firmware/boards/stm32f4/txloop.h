/* The transmit path, shared by both boards: frames from the sampler's ring out on USART1, sleeping (WFI)
 * while the ring is empty. Built with -DFW_TX_MAX_HZ=N it sends at most N frames a second (paced by SysTick
 * at 1 kHz), to force the overrun that a too-slow link would cause (tests/test_firmware.py). */
#ifndef FW_TXLOOP_H
#define FW_TXLOOP_H

#include <stdint.h>

#include "daq.h"

/* Never returns. core_hz: the SysTick clock (the core clock). */
__attribute__((noreturn)) void tx_loop(fw_daq *d, uint32_t core_hz);

#endif
