/* The emulated board, for QEMU's netduinoplus2 machine (STM32F405): the real board's core, USART driver and
 * transmit path, with the ADC and the timer captures replaced by input records (core/input.h), one per
 * sample period, that the simulator writes to QEMU's standard input; the firmware reads them with ARM
 * semihosting (semihost.h), many bytes a call. Each complete record is one sample, so the emulated sample
 * clock is the simulator's stream; the frames go out on USART1 as on the real board.
 *
 * Why not a second USART: QEMU's emulated USART takes its input one byte per pass of QEMU's main loop, two
 * thread wake-ups a byte, which on a loaded host falls seconds behind 500 records a second
 * (firmware/README.md). QEMU models neither the RCC nor the GPIOs of this machine (their registers ignore
 * writes), so the clock tree is not set up; the pin set-up is the real board's and does nothing here. */
#include "daq.h"
#include "gpio.h"
#include "input.h"
#include "regs.h"
#include "semihost.h"
#include "txloop.h"
#include "usart.h"

#define PCLK2_HZ 84000000u
#define DAQ_BAUD 921600u

static fw_daq daq;
static fw_input input;

/* One input byte: a complete record is a sample (the real board's data-ready interrupt). */
static void input_byte(uint8_t byte)
{
    fw_input_record rec;
    fw_input_result r = fw_input_feed(&input, byte, &rec);
    if (r == FW_INPUT_RECORD) {
        if (rec.flags & FW_INPUT_PPS)
            fw_daq_pps(&daq, rec.pps_ticks);
        fw_daq_sample(&daq, rec.counts, rec.sample_ticks, (rec.flags & FW_INPUT_TEMP) != 0, rec.temp_cc);
    } else if (r == FW_INPUT_BAD) {
        fw_daq_sample_bad(&daq);
    }
}

int main(void)
{
    static const char ready[] = "fieldlog-fw emulated ready\n";
    static uint8_t buf[16 * FW_INPUT_SIZE];
    fw_daq_init(&daq);
    fw_input_init(&input);
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOB;
    RCC_APB2ENR |= RCC_APB2ENR_USART1;
    gpio_config(GPIOB_BASE, 6, GPIO_AF, 7);    /* USART1 TX: the frames */
    usart_init(USART1_BASE, PCLK2_HZ, DAQ_BAUD);
    int in = semihost_console(0);
    semihost_write(semihost_console(1), ready, sizeof ready - 1u);   /* the simulator waits for it */
    for (;;) {
        size_t n = semihost_read(in, buf, sizeof buf);
        if (n == 0)
            tx_loop(&daq);   /* the input is gone: sleep */
        for (size_t i = 0; i < n; i++)
            input_byte(buf[i]);
        tx_pump(&daq);
    }
}
