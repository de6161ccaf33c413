/* TIM2, 32 bits at 84 MHz, free running: channel 1 captures the PPS rising edge, channel 2 the ADC's /DRDY
 * falling edge (the sample-clock edge), both in hardware, so the latch does not depend on interrupt
 * latency. /DRDY also raises EXTI1 (the sampling interrupt). */
#ifndef FW_CAPTURE_H
#define FW_CAPTURE_H

#include <stdint.h>

void capture_init(void);

typedef struct {
    uint32_t t_edge;     /* the sample-clock edge's capture */
    uint32_t t_pps;      /* the PPS capture, valid with pps */
    int pps;             /* a PPS edge was captured since the last call */
    int pps_overcapture; /* and more than one */
} capture;

/* Called from the sampling interrupt: the captures since the previous call. */
capture capture_take(void);

#endif
