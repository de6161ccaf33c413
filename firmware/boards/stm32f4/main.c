/* The real board: an STM32F405/407 with a TI ADS131M06 sampling the six analog sensors at 500 Hz and the
 * GPS receiver's 1PPS on a timer capture; frames out on USART1 at 921600 baud (firmware/README.md).
 *
 * The ADC's /DRDY falling edge is the sample clock: TIM2 captures its time, EXTI1 runs the sampling
 * interrupt, which reads the six channels over SPI, takes any PPS capture and hands both to the core
 * sampler (core/daq.h). The main loop only transmits (txloop.c). */
#include "ads131m06.h"
#include "board.h"
#include "capture.h"
#include "clock.h"
#include "daq.h"
#include "gpio.h"
#include "regs.h"
#include "spi.h"
#include "tempsensor.h"
#include "txloop.h"
#include "usart.h"
#include "vectors.h"

static fw_daq daq;

void exti1_handler(void)
{
    EXTI_PR = 1u << 1;
    capture c = capture_take();
    if (c.pps) {
        fw_daq_pps(&daq, c.t_pps);
        if (c.pps_overcapture)
            daq.c.pps_double++;
    }
    int32_t counts[FW_CHANNELS];
    int16_t temp_cc;
    int temp_ok = tempsensor_step(&temp_cc);
    if (ads_read(counts) == 0)
        fw_daq_sample(&daq, counts, c.t_edge, temp_ok, temp_cc);
    else
        fw_daq_sample_bad(&daq);
}

int main(void)
{
    fw_daq_init(&daq);
    clock_init();
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOA | RCC_AHB1ENR_GPIOB;
    RCC_APB1ENR |= RCC_APB1ENR_TIM2;
    RCC_APB2ENR |= RCC_APB2ENR_USART1 | RCC_APB2ENR_SPI1 | RCC_APB2ENR_ADC1 | RCC_APB2ENR_SYSCFG;
    gpio_config(PIN_DAQ_TX, GPIO_AF, 7);
    gpio_config(PIN_PPS, GPIO_AF, 1);
    gpio_config(PIN_DRDY, GPIO_AF, 1);
    gpio_config(PIN_SCK, GPIO_AF, 5);
    gpio_config(PIN_MISO, GPIO_AF, 5);
    gpio_config(PIN_MOSI, GPIO_AF, 5);
    gpio_write(PIN_ADC_CS, 1);
    gpio_write(PIN_ADC_RESET, 1);
    gpio_config(PIN_ADC_CS, GPIO_OUT, 0);
    gpio_config(PIN_ADC_RESET, GPIO_OUT, 0);
    usart_init(USART1_BASE, PCLK2_HZ, DAQ_BAUD);
    spi_init();
    tempsensor_init();
    capture_init();
    ads_init();
    /* /DRDY on PA1 -> EXTI1, falling edge (the pin stays in its TIM2 alternate function: EXTI sees the
     * input of any pin mode) */
    SYSCFG_EXTICR(0) &= ~(0xFu << 4);
    EXTI_FTSR |= 1u << 1;
    EXTI_IMR |= 1u << 1;
    nvic_enable(IRQ_EXTI1, 0);
    tx_loop(&daq);
}
