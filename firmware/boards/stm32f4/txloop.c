#include "txloop.h"

#include "regs.h"
#include "usart.h"

#define USART_DAQ USART1_BASE

#ifdef FW_TX_PER_1000
static uint32_t sent;

static int may_send(const fw_daq *d)
{
    return (uint64_t)sent * 1000u < (uint64_t)d->c.samples * FW_TX_PER_1000;
}
#else
static int may_send(const fw_daq *d)
{
    (void)d;
    return 1;
}
#endif

void tx_pump(fw_daq *d)
{
    uint8_t frame[FW_FRAME_SIZE];
    while (may_send(d) && fw_daq_next_frame(d, frame)) {
#ifdef FW_TX_PER_1000
        sent++;
#endif
        usart_write(USART_DAQ, frame, sizeof frame);
    }
}

void tx_loop(fw_daq *d)
{
    for (;;) {
        /* sleep with interrupts masked, so that one arriving between the test and the WFI still wakes it */
        __asm volatile("cpsid i" ::: "memory");
        if (!may_send(d) || fw_ring_fill(&d->ring) == 0u)
            __asm volatile("wfi" ::: "memory");
        __asm volatile("cpsie i" ::: "memory");
        tx_pump(d);
    }
}
