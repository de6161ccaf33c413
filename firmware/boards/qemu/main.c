/* The emulated board, for QEMU's netduinoplus2 machine (STM32F405): the real board's core, USART driver and
 * transmit path, with the ADC and the timer captures replaced by input records (core/input.h) that the
 * simulator sends on USART2, one per sample period. The USART2 receive interrupt plays the ADC data-ready
 * interrupt: each complete record is one sample, so the emulated sample clock is the simulator's stream.
 *
 * QEMU models neither the RCC nor the GPIOs of this machine (their registers ignore writes), so the clock
 * tree is not set up; the pin set-up is the real board's and does nothing here. */
#include "daq.h"
#include "gpio.h"
#include "input.h"
#include "regs.h"
#include "txloop.h"
#include "usart.h"
#include "vectors.h"

#define CORE_HZ 168000000u   /* QEMU's SysTick clock for this machine */
#define PCLK2_HZ 84000000u
#define PCLK1_HZ 42000000u
#define DAQ_BAUD 921600u

static fw_daq daq;
static fw_input input;

void usart2_handler(void)
{
    while (USART_SR(USART2_BASE) & USART_SR_RXNE) {
        fw_input_record rec;
        fw_input_result r = fw_input_feed(&input, (uint8_t)USART_DR(USART2_BASE), &rec);
        if (r == FW_INPUT_RECORD) {
            if (rec.flags & FW_INPUT_PPS)
                fw_daq_pps(&daq, rec.pps_ticks);
            fw_daq_sample(&daq, rec.counts, rec.sample_ticks, (rec.flags & FW_INPUT_TEMP) != 0, rec.temp_cc);
        } else if (r == FW_INPUT_BAD) {
            fw_daq_sample_bad(&daq);
        }
    }
}

int main(void)
{
    static const uint8_t ready[] = "fieldlog-fw emulated ready\n";
    fw_daq_init(&daq);
    fw_input_init(&input);
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOA | RCC_AHB1ENR_GPIOB;
    RCC_APB1ENR |= RCC_APB1ENR_USART2;
    RCC_APB2ENR |= RCC_APB2ENR_USART1;
    gpio_config(GPIOB_BASE, 6, GPIO_AF, 7);    /* USART1 TX: the frames */
    gpio_config(GPIOA_BASE, 3, GPIO_AF, 7);    /* USART2 RX: the simulator's records */
    gpio_config(GPIOA_BASE, 2, GPIO_AF, 7);    /* USART2 TX: the ready line */
    usart_init(USART1_BASE, PCLK2_HZ, DAQ_BAUD, 0);
    usart_init(USART2_BASE, PCLK1_HZ, DAQ_BAUD, 1);
    nvic_enable(IRQ_USART2, 1);
    usart_write(USART2_BASE, ready, sizeof ready - 1u);   /* the simulator waits for it before it streams */
    tx_loop(&daq, CORE_HZ);
}
